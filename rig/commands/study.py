"""``rig study``: control performance study -> results.md, results.csv, claims.json, PNGs.

    rig study [--config F] [--out DIR] [--quick] [--jobs N | --cluster ADDR] [--no-progress]
"""

from __future__ import annotations

import argparse
import sys

from controller.config import load_config
from rig import argtypes
from rig.terminal import refuse

#: most worker processes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="docs/study", metavar="DIR", type=argtypes.output_dir,
                   help="output directory; its study files are rewritten (default docs/study)")
    p.add_argument("--quick", action="store_true",
                   help="reduced matrix: short runs, 2 Monte Carlo runs (for tests)")
    argtypes.add_batch_options(p)
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    from hil.batch import BatchError, make_executor
    from hil.study.run import run_study
    try:
        with make_executor(args.cluster, args.jobs) as ex:
            res = run_study(cfg, args.out, quick=args.quick, jobs=args.jobs,
                            progress=not args.no_progress, executor=ex)
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
