"""HTML run report of a recording (``rig report``, docs/replay.md).

``write_report(run.mcap, out_dir)`` writes ``out_dir/index.html`` and one PNG per plot
(matplotlib Agg).  The page, top to bottom: what the run was (source, road, blending,
the design's models, each in its own colour), the key of the phase shading used on every
time plot (passive / active / fault latched), passive vs active metrics side by side
(bars and a table), the events as a table (time, code, plain-language reason: a fault's
reason is its :attr:`rig.wire.protocol.FaultCode.description`), then rattlespace, sprung
acceleration, the applied force reference vs the measured force with the tracking error,
why that error is what it is (:mod:`rig.report.tracking`), firing weight and likelihood
quotient q per model, lifecycle with numbered event markers, loop timing, and for an
open-loop replay the recorded vs replayed force reference.  Plot titles are the
recording's message paths (``/rig/signals.force_meas_n``), as a Foxglove Plot panel
writes them, and every ``<figure>`` lists them in ``data-paths``.

The page carries a small inline script that sets ``data-images-loaded="n/m"`` on
``<body>`` once every image has loaded (tests check it in headless Chromium).

Modules: :mod:`~rig.report.series` (decoding, phases), :mod:`~rig.report.metrics`,
:mod:`~rig.report.tracking`, :mod:`~rig.report.events`, :mod:`~rig.report.plots`,
:mod:`~rig.report.page`.
"""

from __future__ import annotations

from rig.report.events import EventRow, event_rows
from rig.report.metrics import phase_metrics, run_metrics
from rig.report.page import write_report
from rig.report.series import Phase, RunSeries, load_series
from rig.report.tracking import ForceTracking, force_tracking

__all__ = ["EventRow", "ForceTracking", "Phase", "RunSeries", "event_rows", "force_tracking",
           "load_series", "phase_metrics", "run_metrics", "write_report"]
