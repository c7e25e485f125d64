"""``rig study``: control performance study -> results.md, results.csv, claims.json, PNGs.

    rig study [--config F] [--out DIR] [--quick] [--groups G,G,... | all]
              [--jobs N | --cluster ADDR] [--no-progress]
"""

from __future__ import annotations

import argparse
import sys

from controller.config import load_config
from rig import argtypes
from rig.terminal import refuse


def groups(text: str) -> tuple[str, ...]:
    """``--groups``: comma-separated names of ``hil.study.matrix.GROUPS``, or ``all``."""
    from hil.study.matrix import GROUPS
    names = [g.strip().lower() for g in text.split(",") if g.strip()]
    if names == ["all"]:
        return GROUPS
    unknown = [g for g in names if g not in GROUPS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"{', '.join(unknown) or 'none given'}: allowed all or a comma-separated list "
            f"of {', '.join(GROUPS)}")
    return tuple(g for g in GROUPS if g in names)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="docs/study", metavar="DIR", type=argtypes.output_dir,
                   help="output directory; its study files are rewritten (default docs/study)")
    p.add_argument("--quick", action="store_true",
                   help="reduced matrix: short runs, 2 Monte Carlo runs (for tests)")
    p.add_argument("--groups", type=groups, default=None, metavar="G,G,...",
                   help="the groups to run, comma-separated, or all (default: all but "
                        "envelope-seeds, the many road seeds of the operating envelope); "
                        "claims.json is written when main runs")
    argtypes.add_batch_options(p)
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    from hil.batch import BatchError, make_executor
    from hil.study.matrix import DEFAULT_GROUPS
    from hil.study.run import run_study
    try:
        with make_executor(args.cluster, args.jobs) as ex:
            res = run_study(cfg, args.out, quick=args.quick, jobs=args.jobs,
                            progress=not args.no_progress, executor=ex,
                            groups=args.groups or DEFAULT_GROUPS)
    except BatchError as exc:
        for failure in exc.failures:
            refuse("study", f"{failure}")
        print(f"rig study: {len(exc.failures)} runs failed; nothing written",
              file=sys.stderr)
        return 1
    print(f"{len(res.rows)} runs in {res.wall_s:.0f} s; skyhook gains {res.skyhook}")
    for claim, measured, ok in res.claims:
        print(f"[{'holds' if ok else 'FAILS'}] {claim}: {measured}")
    for f in res.files:
        print(f"wrote {f}")
    return 0
