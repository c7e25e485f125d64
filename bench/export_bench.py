"""``rig export`` of a 10-minute run: read the recording (``read_run``), build the
columns (``rig.export.run_tables``), write MF4 (asammdf) and Parquet (pyarrow).

The 10-minute recording is synthesised: the tick records and CAN frames of a short
stepped run against the emulated rig (:func:`hil.stepped_run.record_emulated_run`, every
record with the bank's internals) repeated with shifted ticks and times, written by the
recorder as the loop writes them.  ``--quick``: 10 s, one repetition.

    .venv/bin/python -m bench.export_bench [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from controller.config import config_to_toml, default_config

NAME = "export"
TITLE = "rig export of a synthesised run: medians [s] per stage"
PERIOD_NS = 1_000_000


def _synthesise(path: Path, seconds: float, work: Path) -> None:
    from hil.stepped_run import record_emulated_run
    from rig.recording.recorder import RunRecorder
    from rig.recording.run_data import read_run

    src = read_run(record_emulated_run(work / "template.mcap", 1.0))
    cfg = default_config()
    per_tick: dict[int, list[Any]] = {}
    for f in src.frames:
        per_tick.setdefault(f.tick, []).append(f)
    n_src = len(src.records)
    rec = RunRecorder(path, cfg.recording, config_toml=config_to_toml(cfg), design_bytes=None,
                      metadata={"source": "bench.export_bench"}, clock="stepped",
                      clock_offset_ns=1_700_000_000_000_000_000, blocking=True)
    try:
        for k in range(round(seconds * 1e9 / PERIOD_NS)):
            r = src.records[k % n_src]
            t_ns = 1_000_000_000 + k * PERIOD_NS
            for f in per_tick.get(r.tick, ()):
                rec.can_frame(t_ns, k, f.arbitration_id, f.data, f.is_rx)
            rec.tick(t_ns, {**r.data, "tick": k})
    finally:
        rec.close()


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def run(quick: bool = False) -> list[dict[str, Any]]:
    from rig.export import run_tables
    from rig.export.mf4 import write_mf4
    from rig.export.parquet import write_parquet
    from rig.recording.run_data import read_run

    seconds, repeats = (10.0, 1) if quick else (600.0, 3)
    with tempfile.TemporaryDirectory(prefix="export-bench-") as d:
        work = Path(d)
        src = work / "run.mcap"
        t_rec, _ = _timed(lambda: _synthesise(src, seconds, work))
        mcap_mb = sum(p.stat().st_size for p in work.glob("run*.mcap")) / 1e6
        times: dict[str, list[float]] = {"read_run": [], "run_tables": [], "write mf4": [],
                                         "write parquet": []}
        sizes: dict[str, float] = {}
        for i in range(repeats):
            dt, data = _timed(lambda: read_run(src))
            times["read_run"].append(dt)
            dt, tables = _timed(lambda d=data: run_tables(d))
            times["run_tables"].append(dt)
            mf4 = work / f"out{i}.mf4"
            times["write mf4"].append(_timed(lambda t=tables, p=mf4: write_mf4(t, p))[0])
            pq_dir = work / f"pq{i}"
            pq_dir.mkdir()
            times["write parquet"].append(
                _timed(lambda t=tables, p=pq_dir: write_parquet(t, p))[0])
            sizes = {"write mf4": mf4.stat().st_size / 1e6,
                     "write parquet": sum(p.stat().st_size for p in pq_dir.iterdir()) / 1e6}
            n_ticks, n_frames = len(data.records), len(tables.can)
            del data, tables
    rows: list[dict[str, Any]] = [{"stage": "synthesise (recorder)", "median_s": t_rec,
                                   "us_per_tick": t_rec / n_ticks * 1e6, "out_MB": mcap_mb,
                                   "repeats": 1}]
    for stage, ts in times.items():
        med = statistics.median(ts)
        rows.append({"stage": stage, "median_s": med, "us_per_tick": med / n_ticks * 1e6,
                     "out_MB": sizes.get(stage), "repeats": len(ts)})
    for fmt in ("mf4", "parquet"):
        total = sum(statistics.median(times[s]) for s in ("read_run", "run_tables",
                                                          f"write {fmt}"))
        rows.append({"stage": f"= rig export --format {fmt}", "median_s": total,
                     "us_per_tick": total / n_ticks * 1e6, "out_MB": sizes[f"write {fmt}"],
                     "repeats": repeats})
    for r in rows:
        r["ticks"], r["frames"] = n_ticks, n_frames
    return rows


def main(argv: list[str] | None = None) -> int:
    from bench.__main__ import generic_table

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    print(f"{NAME}: {TITLE}")
    print(generic_table(run(quick=args.quick)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
