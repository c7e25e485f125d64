"""``rig replay``: re-run a recorded run (MCAP, or a CAN log .log/.asc/.blf/.mf4) through the
control loop, as fast as the CPU allows (virtual clock).

With the recorded design and configuration the replay must reproduce the recorded
transmitted frames bit for bit (exit status 1 if it does not).  With ``--design`` or
``--config`` it compares the two controllers on the same sensor data -- open loop: the
recorded plant did not react to the replayed commands.  Exit status 2 for a file that
is not a replayable recording (the message names what is wrong) or a ``.mf4`` log without
the ``export`` extra (python-can's MF4 reader needs asammdf, :mod:`rig.extras`); 3 when
the ``--out`` recording could not be written whole (a write failed, e.g. a full disk: the
partial file is kept, readable up to its last complete chunk, and named in one line on
stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from controller.artifact import DesignMismatch, load_design
from controller.config import load_config
from controller.files import regular_file_problem
from rig import argtypes, strict_json
from rig.output_paths import OUTPUT_FAILED
from rig.replay import (
    LOG_SUFFIXES,
    MAX_LOG_SPAN_S,
    RecordingError,
    ReplayResult,
    replay_file,
    require_log_reader,
)
from rig.terminal import refuse, safe


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="recording (.mcap) or python-can log "
                   f"({', '.join(LOG_SUFFIXES)})")
    p.add_argument("--design", metavar="NPZ", default=None, type=argtypes.input_file,
                   help="design artifact to replay with (default: the recorded one)")
    p.add_argument("--out", metavar="MCAP", default=None, type=argtypes.recording_target,
                   help="write the replay as a new recording (a new .mcap path or a "
                        "directory; never overwritten; open it with `rig report`)")
    p.add_argument("--arm-at", type=argtypes.real(0.0, MAX_LOG_SPAN_S, "s"),
                   default=None, metavar="S",
                   help="log files only: arm the controller S seconds after the first frame")
    p.add_argument("--json", action="store_true",
                   help="print the result as strict JSON (null for a non-finite value)")


def _print_text(res: ReplayResult) -> None:
    s = res.summary()
    print(f"replayed {s['ticks']} ticks ({s['recorded_s']:.3f} s recorded) in "
          f"{s['elapsed_s']:.3f} s = {s['realtime_factor']:.1f}x real time; "
          f"{s['rx_frames_fed']} frames fed; final state {s['final_state']}")
    if not res.complete:
        print(f"INCOMPLETE RECORDING: {safe(res.stopped_at)}")
    if res.kind == "mcap":
        verdict = "BIT-EXACT" if res.bit_exact else (
            "DIFFERENT CONTROLLER" if not res.same_controller else "MISMATCH")
        print(f"{verdict}: tx frames {s['tx_frames_compared']} compared, "
              f"{s['tx_frames_mismatched']} differ; max |spool command diff| "
              f"{s['max_abs_command_diff']:.6g}; max |force ref diff| "
              f"{s['max_abs_force_ref_diff_n']:.6g} N")
        if res.bus_exceptions_recorded:
            print(f"bus exceptions: {res.bus_exceptions_recorded} recorded, "
                  f"{res.bus_exceptions_raised} raised again")
        if s["first_mismatch"] and res.same_controller:
            print(f"first mismatch: {json.dumps(s['first_mismatch'])}")
    if res.comparison:
        c = res.comparison
        print("comparison (recorded vs replayed controller):")
        for key in ("force_ref_rms_recorded_n", "force_ref_rms_replayed_n",
                    "force_ref_rms_difference_n", "force_ref_correlation",
                    "spool_rms_recorded", "spool_rms_replayed", "active_ticks_recorded",
                    "active_ticks_replayed", "faults_recorded", "faults_replayed"):
            v = c[key]
            print(f"  {key:28s} {v:.6g}" if isinstance(v, float) else f"  {key:28s} {v}")
    for note in res.notes:
        print(f"note: {safe(note)}")
    if res.out and not res.out_error:
        print(f"wrote {res.out}")


def run(args: argparse.Namespace) -> int:
    path = Path(args.run)
    is_log = path.suffix.lower() in LOG_SUFFIXES
    not_regular = regular_file_problem(path)
    if not_regular:          # a FIFO would block the reader
        refuse("replay", f"{path}: {not_regular}")
        return 2
    if args.arm_at is not None and not is_log:
        refuse("replay", f"--arm-at applies to log files ({', '.join(LOG_SUFFIXES)}) "
                         f"only; {path.name} replays its recorded commands")
        return 2
    require_log_reader(path)     # before the design: .mf4 needs the 'export' extra
    try:
        cfg = load_config(args.config) if (args.config or is_log) else None
        design = design_bytes = None
        if args.design:
            design_bytes = Path(args.design).read_bytes()
            design = load_design(args.design, cfg)
        elif is_log:
            from rig.design_cache import design_for

            assert cfg is not None
            design = design_for(cfg)
        elif cfg is not None:
            design = _matching_design(path, cfg)
        res = replay_file(path, cfg=cfg, design=design, design_bytes=design_bytes,
                          out=args.out, arm_at_s=args.arm_at)
    except (RecordingError, DesignMismatch) as exc:
        refuse("replay", f"{exc}")
        return 2
    if args.json:
        print(strict_json.dumps(res.summary(), indent=1))
    else:
        _print_text(res)
    if res.out_error:        # a full disk: the output was the point
        refuse("replay", f"{res.out} is incomplete: {res.out_error}")
        return OUTPUT_FAILED
    if res.kind == "mcap" and res.same_controller and not res.bit_exact:
        return 1
    return 0


def _matching_design(path: Path, cfg: Any) -> Any:
    """--config without --design: the recorded design if it was made for this
    configuration, else a fresh design for it (``rig design``'s result)."""
    from controller.config import config_hash
    from rig.design_cache import design_for
    from rig.replay import load_recorded_run, recorded_design

    rec = recorded_design(load_recorded_run(path))
    if rec.metadata.get("config_hash") == config_hash(cfg):
        return rec
    print("rig replay: the recorded design was made for another configuration; "
          "designing for --config", file=sys.stderr)
    return design_for(cfg)
