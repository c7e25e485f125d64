"""Control performance study (issue 6): the thesis's claims against the alternatives.

``run_study(cfg, out_dir, quick=..., jobs=...)`` (:mod:`hil.study.run`) runs the matrix of
:mod:`hil.study.matrix` in parallel through :func:`hil.sim.closed_loop.run_closed_loop` (the one
simulator tick loop) and writes the tables and figures of :mod:`hil.study.report`;
``rig study`` is its CLI.
"""
