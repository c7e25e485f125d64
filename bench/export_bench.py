"""``rig export`` of a 10-minute run: per format, the median wall time of a few exports,
its ratio to the run's duration, the output size, the export's peak RSS and the median
of each stage (:data:`rig.export.stream.STAGES`).

The recording is a real one: 600 s of the loop against the emulated rig, tick-stepped
in-process (:func:`hil.stepped_run.record_emulated_run`: the same ``ControlLoop`` and
``RunRecorder`` as ``rig demo --record``, default configuration, rough course, armed
after 0.1 s; about a minute to build), cached under ``build/export-bench/`` (the name
carries the recording format version; delete the directory to rebuild it).  Each export
runs in a child process of its own (``--child``), as ``rig export`` would, so that its
peak RSS (``ru_maxrss``) is its own; the runs are interleaved between the formats.
``--quick``: a 20 s recording, one export per format.

    .venv/bin/python -m bench.export_bench [--quick] [--runs N] [--formats mf4,csv]
"""

from __future__ import annotations

import argparse
import importlib
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Final

NAME = "export"
TITLE = "rig export of a recorded run (each export in a child process)"
ROOT: Final = Path(__file__).resolve().parent.parent
CACHE: Final = ROOT / "build" / "export-bench"
FULL_S, QUICK_S = 600.0, 20.0
FULL_RUNS = 3
#: format -> the module of its writer (rig/export/)
WRITER_MODULES: Final = {"mf4": "rig.export.mf4", "parquet": "rig.export.parquet",
                         "csv": "rig.export.csv_files"}


def recording(seconds: float) -> tuple[Path, float | None]:
    """The cached recording of ``seconds`` (built now if missing) and the seconds it
    took to build (None: it was cached)."""
    from rig.recording.schema import RECORDING_FORMAT_VERSION

    path = CACHE / f"stepped-{seconds:g}s-format{RECORDING_FORMAT_VERSION}.mcap"
    if path.exists():
        return path, None
    from hil.stepped_run import record_emulated_run

    CACHE.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial.mcap")   # a .mcap name: a file, not
    # a directory that gets run-<UTC>.mcap (rig.recording.recorder.recording_file)
    partial.unlink(missing_ok=True)
    t = time.perf_counter()
    record_emulated_run(partial, seconds)
    built_s = time.perf_counter() - t
    partial.rename(path)
    return path, built_s


def _size_mb(path: Path) -> float:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.iterdir()) / 1e6
    return path.stat().st_size / 1e6


def _clear(out: Path) -> None:
    if out.is_dir():
        shutil.rmtree(out)
    else:
        out.unlink(missing_ok=True)


def export_once(src: Path, fmt: str, out: Path) -> dict[str, Any]:
    """One export in a child process: its figures (:func:`child`) and the command's
    wall time with the interpreter's start and the imports (``cmd_s``)."""
    _clear(out)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "bench.export_bench", "--child", fmt,
                           str(src), str(out)], cwd=ROOT, capture_output=True, text=True,
                          check=False)
    cmd_s = time.perf_counter() - t
    if proc.returncode:
        raise RuntimeError(f"export {fmt} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    figures: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    figures["cmd_s"] = cmd_s
    figures["out_MB"] = _size_mb(out)
    return figures


def child(fmt: str, src: str, out: str) -> None:
    """Run one export (``export_run``, as ``rig export`` does, without the staging) and
    print its figures as a JSON line: wall seconds, seconds per stage, peak RSS after
    the imports and at the end [MB] (``ru_maxrss``, this process)."""
    import resource

    from rig.export.stream import export_run

    importlib.import_module(WRITER_MODULES[fmt])    # the writer's imports, counted apart
    if fmt != "mf4":                                  # parquet, csv: a directory
        Path(out).mkdir()

    def peak_mb() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # KiB on Linux

    imports_mb = peak_mb()
    t = time.perf_counter()
    summary = export_run(src, fmt, out, comment="bench.export_bench")
    wall_s = time.perf_counter() - t
    print(json.dumps({"wall_s": wall_s, "stage_s": summary.stage_s, "imports_MB": imports_mb,
                      "peak_MB": peak_mb(), "records": summary.records,
                      "frames": summary.frames, "batches": summary.batches}))


def run(quick: bool = False, runs: int | None = None,
        formats: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
    from rig.commands.export import FORMATS
    from rig.export.stream import STAGES

    formats = formats or FORMATS

    seconds = QUICK_S if quick else FULL_S
    runs = runs or (1 if quick else FULL_RUNS)
    src, built_s = recording(seconds)
    out_dir = CACHE / "out"
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, list[dict[str, Any]]] = {fmt: [] for fmt in formats}
    for _ in range(runs):                             # interleaved: same drift for all
        for fmt in formats:
            out = out_dir / (f"run.{fmt}" if fmt == "mf4" else fmt)
            results[fmt].append(export_once(src, fmt, out))
    stage_cols = [f"{stage}_s" for stage in STAGES]
    cols = ["format", "runs", "median_s", "x_duration", "cmd_s", *stage_cols, "out_MB",
            "peak_RSS_MB", "imports_RSS_MB", "note"]
    rows: list[dict[str, Any]] = [dict.fromkeys(cols) | {
        "format": "(recording)", "runs": 1, "median_s": built_s, "out_MB": _size_mb(src),
        "note": f"{seconds:g} s stepped run, {'built now' if built_s else 'cached'}"}]
    for fmt, figs in results.items():
        med = statistics.median(f["wall_s"] for f in figs)
        row: dict[str, Any] = dict.fromkeys(cols) | {
            "format": fmt, "runs": len(figs), "median_s": med, "x_duration": med / seconds,
            "cmd_s": statistics.median(f["cmd_s"] for f in figs),
            "out_MB": statistics.median(f["out_MB"] for f in figs),
            "peak_RSS_MB": max(f["peak_MB"] for f in figs),
            "imports_RSS_MB": statistics.median(f["imports_MB"] for f in figs),
            "note": (f"{figs[0]['records']} ticks, {figs[0]['frames']} frames, "
                     f"{figs[0]['batches']} batches")}
        for stage, col in zip(STAGES, stage_cols, strict=True):
            row[col] = statistics.median(f["stage_s"][stage] for f in figs)
        rows.append(row)
    return rows


def notes(rows: list[dict[str, Any]]) -> list[str]:
    return ["median_s: export_run in the child (cmd_s: the whole command with the "
            "interpreter's start and imports); x_duration: median_s / the run's duration; "
            "peak_RSS_MB: the child's ru_maxrss (max over the runs), imports_RSS_MB: "
            "the same right after the imports; *_s: per-stage medians "
            "(rig.export.stream.STAGES)"]


def main(argv: list[str] | None = None) -> int:
    from bench.__main__ import generic_table

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--runs", type=int, help=f"exports per format (default {FULL_RUNS}, "
                                            "1 with --quick)")
    p.add_argument("--formats", help="comma-separated (default: every format of rig export)")
    p.add_argument("--child", nargs=3, metavar=("FORMAT", "SRC", "OUT"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    print(f"{NAME}: {TITLE}")
    rows = run(quick=args.quick, runs=args.runs,
               formats=tuple(args.formats.split(",")) if args.formats else None)
    print(generic_table(rows))
    print("\n".join(notes(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
