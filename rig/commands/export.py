"""``rig export RUN.mcap --format mf4|parquet|csv --out PATH [--force]``: a recording for
measurement tools (docs/recording.md, "Export").

``mf4``: one ASAM MDF 4 file, a channel group per tick topic (SI units) and the CAN bus
log as ``CAN_DataFrame`` bus-logging groups (CANape, asammdf, python-can decode it with
``rig/wire/rig.dbc``, attached).  ``parquet``: a directory with a file per tick topic
and ``can.parquet``; ``csv``: the same tables as CSV files.  The output is written under
a hidden name next to it and renamed when complete (a failure leaves no partial output);
an existing output is replaced only with ``--force``.  The writers (asammdf, pyarrow)
are the ``export`` extra of the distribution (:mod:`rig.extras`): without it the
command says so in one line, exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Final

from rig import argtypes
from rig.output_paths import new_file_problem, output_dir_problem, staged_dir, staged_file
from rig.terminal import refuse, safe

FORMATS: Final = ("mf4", "parquet", "csv")
MF4_SUFFIX: Final = ".mf4"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", type=argtypes.input_file,
                   help="recording (.mcap, its first segment)")
    p.add_argument("--format", required=True, choices=FORMATS,
                   help="mf4: one ASAM MDF 4 file (signals + CAN bus log); parquet: a "
                        "directory, one file per topic + can.parquet; csv: the same as "
                        "CSV files (each needs the 'export' extra)")
    p.add_argument("--out", metavar="PATH", required=True,
                   help=f"mf4: a {MF4_SUFFIX} file; parquet, csv: a directory")
    p.add_argument("--force", action="store_true",
                   help="replace an existing output")


def output_problem(fmt: str, out: Path, force: bool) -> str | None:
    """Why ``out`` cannot take the export, or None."""
    if fmt == "mf4":
        if out.suffix.lower() != MF4_SUFFIX:
            return f"--out {out}: an mf4 export is a {MF4_SUFFIX} file"
        problem = new_file_problem(out, force=force)
    else:
        problem = output_dir_problem(out)
        if problem is None and out.is_dir() and any(out.iterdir()) and not force:
            problem = "exists: add --force to replace its files"
    return None if problem is None else f"--out {out}: {problem}"


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    problem = output_problem(args.format, out, args.force)
    if problem:
        refuse("export", problem)
        return 2
    from rig.export.stream import export_run

    t_start = time.perf_counter()
    stage_of = staged_file if args.format == "mf4" else staged_dir
    with stage_of(out) as stage:
        summary = export_run(args.run, args.format, stage,
                             comment=f"rig export of {Path(args.run).name}")
    if not summary.run.complete:
        print(f"rig export: INCOMPLETE RECORDING (exported what was read): "
              f"{safe(summary.run.stopped_at)}", file=sys.stderr)
    elapsed = time.perf_counter() - t_start
    print(f"wrote {out} ({args.format}): {summary.records} tick records in "
          f"{summary.topics} topics, {summary.frames} CAN frames, {elapsed:.2f} s")
    if summary.skipped:
        print(f"not numeric, left out: {', '.join(summary.skipped)}")
    return 0
