"""``rig report RUN.mcap [--out DIR]``: HTML page with PNG plots and summary metrics of a
recorded run (``rig.report``).  Exit status 2 for a file that is not a recording."""

from __future__ import annotations

import argparse

from rig import argtypes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="recording (.mcap)")
    p.add_argument("--out", metavar="DIR", default=None, type=argtypes.output_dir,
                   help="output directory, its report files rewritten "
                        "(default: <RUN stem>-report next to RUN)")
    p.add_argument("--compare", metavar="MCAP", default=None, type=argtypes.input_file,
                   help="another recording of the same data to plot side by side "
                        "(default for a replay: its source recording)")


def run(args: argparse.Namespace) -> int:
    from rig.report import write_report

    index = write_report(args.run, args.out, args.compare)
    print(f"wrote {index}")
    return 0
