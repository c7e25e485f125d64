"""Replay speed: how much faster than real time ``rig replay`` re-runs a 1 kHz recording.

``python -m bench.replay_bench [--seconds S] [--minutes-target 10]`` records S seconds of
the controller loop, tick-stepped against the emulated rig on a virtual bus with the
recorder on (:func:`hil.stepped_run.record_emulated_run`), replays it
three times and prints the median replay time, the real-time factor and the time
scaled to a 10-minute recording (the target: under 12 s, i.e. 50x real time), plus a
profile split (reading the MCAP vs ticking the loop).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
import tempfile
import time
from pathlib import Path

from hil.stepped_run import record_emulated_run
from rig.replay import load_recorded_run, replay_recording


def _profile(path: Path) -> str:
    pr = cProfile.Profile()
    pr.enable()
    replay_recording(path)
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(12)
    return s.getvalue()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="recording length [s]")
    ap.add_argument("--minutes-target", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--keep", default=None, help="keep the recording at this path")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        path = Path(args.keep) if args.keep else Path(d) / "bench.mcap"
        t0 = time.perf_counter()
        record_emulated_run(path, args.seconds)
        t_rec = time.perf_counter() - t0
        size = path.stat().st_size
        t0 = time.perf_counter()
        run = load_recorded_run(path)
        t_read = time.perf_counter() - t0
        print(f"recording: {args.seconds:g} s at 1 kHz ({run.tick.size} ticks, "
              f"{size / 1e6:.1f} MB, {len(run.rx)} rx / {len(run.tx)} tx frames), "
              f"written in {t_rec:.1f} s")
        print(f"read alone (scan + decode): {t_read:.2f} s = "
              f"{1e6 * t_read / run.tick.size:.1f} us/tick")
        res = None
        for label, reader in (("in-process read", False), ("reader process", True)):
            times, loops = [], []
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                res = replay_recording(path, reader_process=reader)
                times.append(time.perf_counter() - t0)
                loops.append(res.elapsed_s)
            med = statistics.median(times)
            loop_s = statistics.median(loops)
            scaled = med * args.minutes_target * 60.0 / args.seconds
            print(f"{label:16s}: replay {med:.2f} s (median of {args.repeat}) = "
                  f"{1e6 * med / run.tick.size:.1f} us/tick, {args.seconds / med:.1f}x real "
                  f"time, scaled to {args.minutes_target:g} min {scaled:.1f} s (target < 12 s);"
                  f" loop part {loop_s:.2f} s = {1e6 * loop_s / run.tick.size:.1f} us/tick")
        assert res is not None
        print(f"bit exact: {res.bit_exact} (max_abs_command_diff "
              f"{res.max_abs_command_diff}, {res.tx_frames_compared} tx frames compared)")
        if args.profile:
            print(_profile(path))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
