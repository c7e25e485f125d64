"""``rig identify RUN.mcap [--json] [--out FITTED.toml] [--report FILE.html]``: identify the
rig from an identification run (``rig run --excite`` / ``rig demo --excite``;
docs/identify.md).

The recording is read with the run report's reader (:func:`rig.report.series.load_series`):
the LVDT, load cell and accelerometer readings, the spool command and force reference per
tick, its configuration (``config.toml`` attachment) and the ``excitation`` events.  The
excitation segment is the ticks from the ``start`` event to its ``end`` (or ``aborted``)
with the valve driven; the rest is the passive ticks before it (valve safe, INACTIVE or
FAULT: the rig is still either way).  The math is
:mod:`controller.identify`.

Output: a table (estimate, 95 % interval, relative half width; what was not identified
and why; the frequency-domain cross-check), or with ``--json``
``{"estimates": {config key: value}, "ci95": {key: [lo, hi]}, "fit": {...},
"recording": {"complete", "stopped_at", "excitation_ended"}}``; a recording that was
not read whole (cut, damaged) or whose excitation has no end event is fitted from what
it holds and said to be incomplete (``INCOMPLETE RECORDING: ...`` first in the table
and in the ``--out`` file's header).  ``--out``
writes the recorded configuration with the estimates in (a file ``rig design --config``
takes as is); ``--report`` an HTML page (measured vs fitted Bode, traces, residuals).
A run that cannot be identified is refused in one line (exit status 2).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from rig import argtypes, strict_json
from rig.terminal import refuse, safe


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", type=argtypes.input_file,
                   help="recording of an identification run (.mcap)")
    p.add_argument("--json", action="store_true",
                   help="print estimates, 95 %% intervals and fit details as strict JSON")
    p.add_argument("--out", metavar="FITTED.toml", default=None, type=argtypes.output_file,
                   help="write the recorded configuration with the identified values "
                        "(`rig design --config FITTED.toml`); an existing file only with "
                        "--force")
    p.add_argument("--report", metavar="FILE.html", default=None, type=argtypes.output_file,
                   help="write an HTML report (measured vs fitted responses, traces, "
                        "residuals); an existing file only with --force")
    p.add_argument("--force", action="store_true", help="replace --out / --report files")


def run_data(series: Any) -> Any:
    """:class:`controller.identify.RunData` of a recording's series; refused (one line)
    when it has no excitation segment."""
    from controller.identify import IdentificationRefusedError, RunData

    n = series.tick.size
    starts = [e for e in series.events if e.get("kind") == "excitation"
              and isinstance(e.get("detail"), dict) and e["detail"].get("phase") == "start"]
    if not starts or n == 0:
        raise IdentificationRefusedError(
            "no excitation segment: the recording has no 'excitation' start event (record "
            "an identification run with `rig run --excite` or `rig demo --excite`)")
    t0 = int(starts[0]["tick"])
    ends = [int(e["tick"]) for e in series.events if e.get("kind") == "excitation"
            and isinstance(e.get("detail"), dict)
            and e["detail"].get("phase") in ("end", "aborted") and int(e["tick"]) >= t0]
    t1 = ends[0] if ends else int(series.tick[-1]) + 1
    sig = series.signals
    enabled = sig["valve_enable"] > 0
    excite = (series.tick >= t0) & (series.tick < t1) & enabled
    # passive (valve safe: INACTIVE, or FAULT latched) with the road at rest
    passive = np.array([lc in ("INACTIVE", "FAULT") for lc in series.lifecycle], dtype=bool)
    rest = (series.tick < t0) & ~enabled & passive

    def col(name: str) -> np.ndarray:
        x = np.asarray(sig[name], dtype=np.float64)
        return np.where(np.isfinite(x), x, 0.0) if name == "spool_cmd" else x

    # a tick got the next sample when the 4-bit counter advanced by one and the sample
    # is new (age 0) and the loop did not skip a period
    counter = np.nan_to_num(sig["sensor_counter"], nan=-1.0).astype(np.int64)
    step = (np.diff(counter) % 16 == 1) & (np.diff(series.tick) == 1)
    period = np.diff(series.t_s)
    step &= np.abs(period - series.dt_s) < 0.5 * series.dt_s
    fresh = np.r_[True, step] & (np.nan_to_num(sig["sensor_age_ticks"], nan=1.0) == 0)
    return RunData(series.dt_s, col("rattlespace_m"), col("sprung_accel_mps2"),
                   col("force_meas_n"), col("force_ref_n"), col("spool_cmd"), excite, rest,
                   fresh)


def _fmt(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.6g}"


def summary_json(ident: Any, series: Any) -> dict[str, Any]:
    return {"estimates": dict(ident.estimates),
            "ci95": {k: [lo, hi] for k, (lo, hi) in ident.ci95.items()},
            "fit": ident.fit, "recording": recording_state(series)}


def recording_state(series: Any) -> dict[str, Any]:
    """Whether the recording was read whole: ``complete``, ``stopped_at`` (where and
    why reading stopped, None when complete) and ``excitation_ended`` (its end or
    aborted event is in the recording: a file cut during the excitation has none)."""
    ended = any(e.get("kind") == "excitation" and isinstance(e.get("detail"), dict)
                and e["detail"].get("phase") in ("end", "aborted") for e in series.events)
    return {"complete": bool(series.scan.complete), "stopped_at": series.scan.stopped_at,
            "excitation_ended": ended}


def incomplete_note(state: dict[str, Any]) -> str | None:
    """The line that says the fit used an incomplete recording, or None."""
    if state["complete"] and state["excitation_ended"]:
        return None
    cut = "" if state["excitation_ended"] else \
        "; the excitation has no end event: the fit used the part recorded"
    return f"INCOMPLETE RECORDING: {safe(state['stopped_at'] or 'not read whole')}{cut}"


def run(args: argparse.Namespace) -> int:
    from controller.config import config_to_toml
    from controller.identify import IdentificationRefusedError, fitted_config, identify
    from rig.report.series import load_series

    series = load_series(args.run)      # RecordingError: rig.cli.REFUSALS
    if series.config is None:
        refuse("identify", f"{args.run}: {series.config_problem}")
        return 2
    cfg = series.config
    try:
        ident = identify(run_data(series), cfg)
    except IdentificationRefusedError as exc:
        refuse("identify", f"{args.run}: {exc}")
        return 2
    state = recording_state(series)
    note = incomplete_note(state)
    if args.out:
        fitted = fitted_config(cfg, ident)
        Path(args.out).write_text(
            f"# identified by `rig identify {Path(args.run).name}`; the keys not identified "
            "are the recording's\n" + ("" if note is None else f"# {note}\n")
            + config_to_toml(fitted), encoding="utf-8")
    if args.report:
        from rig.report.identify import write_identify_report

        write_identify_report(ident, args.report, Path(args.run).name)
    if args.json:
        print(strict_json.dumps(summary_json(ident, series)))
        return 0
    if note:
        print(note)
    print(f"rig identify: {args.run}: {ident.fit['excitation_s']:.1f} s of excitation, "
          f"{ident.fit['rest_s']:.1f} s of rest")
    gaps = ident.fit["gaps"]
    if gaps["gaps"]:
        print(f"missed sensor samples: {gaps['missed_sensor_samples']} ticks in {gaps['gaps']} "
              f"gaps; the filters restart after each and settle "
              f"{gaps['segment_settle_s']:g} s: {gaps['left_out_s']:.2f} s "
              f"({100 * gaps['left_out_fraction']:.1f} %) of the excitation left out")
    print(f"{'key':40} {'estimate':>12} {'95 % interval':>27} {'+/- %':>7}")
    for key, value in ident.estimates.items():
        lo, hi = ident.ci95[key]
        rel = (100 * (hi - lo) / 2 / abs(value) if abs(value) > (hi - lo) / 2
               else math.nan)       # an offset near 0: no relative width
        print(f"{key:40} {_fmt(value):>12} [{_fmt(lo):>12}, {_fmt(hi):>12}] "
              f"{'' if not math.isfinite(rel) else f'{rel:.2f}':>7}")
    for key, why in ident.not_identified.items():
        print(f"{key}: {why}")
    fd = ident.fit["frequency_domain"]["relative_difference"]
    print("frequency-domain cross-check (Welch, relative to the time domain): "
          + ", ".join(f"{k.split('.')[-1]} {100 * v:+.2f} %" for k, v in fd.items()))
    if args.out:
        print(f"wrote {args.out}")
    if args.report:
        print(f"wrote {args.report}")
    return 0
