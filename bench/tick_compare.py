"""``python -m bench.tick_compare REV [--rounds N] [--ticks N]``: the control loop's tick on
this tree against the tree of git revision ``REV``, both in one run.

A timing on this machine moves by 30 % from one hour to the next (the host's load, its
real-time stalls, the CPU's clock), so "no worse than before" means the two trees timed
in the same session, turn about.  This exports ``REV`` (``git archive``) into a
temporary directory and runs :func:`bench.loop_bench.tick_hot_and_cold` (the default
configuration's ``ControlLoop.tick`` on the emulated rig's socket pair, armed, in a plain
thread: back to back, and 0.8 ms apart as after the loop's sleep) in a fresh process per
turn, alternating the two trees for ``--rounds`` rounds.  It prints the median of each
figure over the turns and the ratio this tree / ``REV``.

``REV`` must have ``bench.loop_bench.tick_hot_and_cold(cfg, design_path, n)`` (since
2026-11: ``git log -S tick_hot_and_cold -- bench/loop_bench.py``).  Both trees run with
this checkout's virtual environment.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ("hot_p50_us", "hot_p99_us", "cold_p50_us", "cold_p99_us")

# one turn, run with the tree as working directory and PYTHONPATH (its packages first)
_TURN = """
import json, os, sys, tempfile
from bench.loop_bench import tick_hot_and_cold
from controller.artifact import save_design
from controller.config import default_config
from hil.sim.closed_loop import cached_design
cfg = default_config()
with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "design.npz")
    save_design(cached_design(cfg), path)
    out = tick_hot_and_cold(cfg, path, n=int(sys.argv[1]))
print("TURN " + json.dumps(out))
"""


def export_tree(rev: str, dest: Path) -> str:
    """``rev``'s files into ``dest``; its full commit hash.  ValueError for an unknown
    revision."""
    res = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                         cwd=ROOT, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise ValueError(f"tick_compare: {rev!r} is not a commit of {ROOT}")
    commit = res.stdout.strip()
    tar = subprocess.run(["git", "archive", "--format=tar", commit], cwd=ROOT,
                         capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
        tf.extractall(dest, filter="data")
    return commit


def turn(tree: Path, ticks: int) -> dict[str, float]:
    """One turn of ``tick_hot_and_cold`` in a fresh process in ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    res = subprocess.run([sys.executable, "-c", _TURN, str(ticks)], cwd=tree, env=env,
                         capture_output=True, text=True, check=False)
    for line in res.stdout.splitlines():
        if line.startswith("TURN "):
            return {k: float(v) for k, v in json.loads(line[5:]).items()}
    tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
    raise RuntimeError(f"tick_compare: the turn in {tree} failed: {tail}")


def compare(rev: str, rounds: int, ticks: int) -> str:
    """The table: medians over ``rounds`` alternating turns of each tree."""
    # next to this checkout, so that ``../shared`` means the same for both trees
    with tempfile.TemporaryDirectory(prefix=".tick-compare-", dir=ROOT.parent) as tmp:
        old = Path(tmp) / "tree"
        commit = export_tree(rev, old)
        turns: dict[str, list[dict[str, float]]] = {"this": [], "rev": []}
        for _ in range(rounds):
            turns["rev"].append(turn(old, ticks))
            turns["this"].append(turn(ROOT, ticks))
    med = {k: {f: float(np.median([t[f] for t in ts])) for f in FIGURES}
           for k, ts in turns.items()}
    lines = [f"ControlLoop.tick, default configuration, {ticks} ticks per figure, medians of "
             f"{rounds} alternating turns (fresh process each)",
             f"{'':22}{'this tree':>12}{commit[:10]:>12}{'ratio':>8}"]
    for f in FIGURES:
        a, b = med["this"][f], med["rev"][f]
        lines.append(f"{f + ' [us]':22}{a:12.1f}{b:12.1f}{a / b if b else float('nan'):8.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.tick_compare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rev", help="the git revision to compare against")
    ap.add_argument("--rounds", type=int, default=5, help="turns of each tree (default 5)")
    ap.add_argument("--ticks", type=int, default=3000,
                    help="ticks per figure and turn (default 3000)")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.ticks < 100:
        ap.error("--rounds at least 1, --ticks at least 100")
    try:
        print(compare(args.rev, args.rounds, args.ticks))
    except (ValueError, RuntimeError) as exc:
        print(exc, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
