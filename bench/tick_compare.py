"""``python -m bench.tick_compare REV [--rounds N] [--ticks N | --loop SECONDS]``: the control
loop's tick on this tree against the tree of git revision ``REV``, both in one run.

A timing on this machine moves by 30 % from one hour to the next (the host's load, its
real-time stalls, the CPU's clock), so "no worse than before" means the two trees timed
in the same session, turn about.  This exports ``REV`` (``git archive``) into a
temporary directory and runs :func:`bench.loop_bench.tick_hot_and_cold` (the default
configuration's ``ControlLoop.tick`` on the emulated rig's socket pair, armed, in a plain
thread: back to back, and 0.8 ms apart as after the loop's sleep) in a fresh process per
turn, alternating the two trees for ``--rounds`` rounds.  It prints the median of each
figure over the turns and the ratio this tree / ``REV``.

With ``--loop SECONDS`` a turn is the loop bench instead (:func:`bench.loop_bench.measure`
of the cases ``bare`` and ``rec+tel``, ``SECONDS`` each: the service's real-time loop
against the emulated rig in its own process, without the bench's micro-measurements):
the step time p50 / p99 of each case (wake-up to end of tick), its periods late and its
faults, then turn by turn the faults' names with the turn's largest lateness of the
loop and of the emulated rig (a fault in a turn where either reached milliseconds is
the host stalling that process past the sensor timeout, either tree);
``--cpu N`` pins the loop to CPU N as ``deploy/rig.service`` does (the bench's ``--cpu``:
the emulated rig and the service's helpers then run on the other CPUs).

``REV`` must have ``bench.loop_bench.tick_hot_and_cold(cfg, design_path, n)`` (since
2026-11: ``git log -S tick_hot_and_cold -- bench/loop_bench.py``), or for ``--loop``
``bench.loop_bench.measure(seconds, cases)``.  Both trees run with this checkout's
virtual environment.
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
LOOP_CASES = ("bare", "rec+tel")
LOOP_FIGURES = tuple(f"{case} {f}" for case in LOOP_CASES
                     for f in ("step_p50_us", "step_p99_us", "periods_late_pct", "faults"))

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

# one turn of the loop bench (the micro-measurements left out: they are the tick turns')
_LOOP_TURN = """
import json, sys
import bench.loop_bench as lb
lb.tick_with_and_without_preview = lambda *a, **k: ({}, {})
lb.tick_hot_and_cold = lambda *a, **k: {}
lb.bus_cost = lambda *a, **k: {}
lb.sleep_lateness = lambda *a, **k: {}
cpu = int(sys.argv[3]) if sys.argv[3] else None
res = lb.measure(float(sys.argv[1]), sys.argv[2].split(","), cpu=cpu)
out, names = {}, {}
for case, c in res["cases"].items():
    for f in ("step_p50_us", "step_p99_us", "periods_late_pct"):
        out[case + " " + f] = c[f]
    out[case + " lateness_max_us"] = c.get("lateness_max_us", float("nan"))
    out[case + " rig_lateness_max_us"] = c.get("rig_max_lateness_us", float("nan"))
    faults = c.get("faults", 0)
    out[case + " faults"] = len(faults) if isinstance(faults, list) else faults
    names[case] = [str(f) for f in faults] if isinstance(faults, list) else []
print("TURN " + json.dumps(out))
print("FAULTS " + json.dumps(names))
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


def turn(tree: Path, ticks: int, loop_s: float = 0.0, cpu: int | None = None
         ) -> tuple[dict[str, float], dict[str, list[str]]]:
    """One turn of ``tick_hot_and_cold`` (or with ``loop_s``, of the loop bench, its loop
    pinned to ``cpu`` when given) in a fresh process in ``tree``: its figures, and for a
    loop turn the names of the faults each case latched (the tick turn has none)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    args = ([_LOOP_TURN, str(loop_s), ",".join(LOOP_CASES), "" if cpu is None else str(cpu)]
            if loop_s > 0
            else [_TURN, str(ticks)])
    res = subprocess.run([sys.executable, "-c", *args], cwd=tree, env=env,
                         capture_output=True, text=True, check=False)
    figures: dict[str, float] | None = None
    faults: dict[str, list[str]] = {}
    for line in res.stdout.splitlines():
        if line.startswith("TURN "):
            figures = {k: float(v) for k, v in json.loads(line[5:]).items()}
        elif line.startswith("FAULTS "):
            faults = {k: [str(f) for f in v] for k, v in json.loads(line[7:]).items()}
    if figures is None:
        tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"tick_compare: the turn in {tree} failed: {tail}")
    return figures, faults


def fault_lines(turns: dict[str, list[tuple[dict[str, float], dict[str, list[str]]]]],
                commit: str) -> list[str]:
    """Per case and tree, turn by turn: the faults latched (by name, "-" for none), the
    loop's largest lateness and the emulated rig's [us] -- a SENSOR_STALE in a turn
    where either reached milliseconds is the host stalling that process past the sensor
    timeout (2 ticks), not the tree's tick."""
    nan = float("nan")
    lines = []
    for case in LOOP_CASES:
        for who, label in (("this", "this tree"), ("rev", commit[:10])):
            cells = []
            for figures, faults in turns[who]:
                names = faults.get(case, [])
                late = figures.get(f"{case} lateness_max_us", nan)
                rig = figures.get(f"{case} rig_lateness_max_us", nan)
                cells.append(f"{'+'.join(names) or '-'} ({late:.0f} / {rig:.0f})")
            lines.append(f"{case} faults (lateness max of the loop / the rig [us]), {label}: "
                         + ", ".join(cells))
    return lines


def compare(rev: str, rounds: int, ticks: int, loop_s: float = 0.0,
            cpu: int | None = None) -> str:
    """The table: medians over ``rounds`` alternating turns of each tree (``loop_s`` > 0:
    loop bench turns of that many seconds per case, the loop on ``cpu`` when given)."""
    figures = LOOP_FIGURES if loop_s > 0 else FIGURES
    # next to this checkout, so that ``../shared`` means the same for both trees
    with tempfile.TemporaryDirectory(prefix=".tick-compare-", dir=ROOT.parent) as tmp:
        old = Path(tmp) / "tree"
        commit = export_tree(rev, old)
        turns: dict[str, list[tuple[dict[str, float], dict[str, list[str]]]]] = {
            "this": [], "rev": []}
        for _ in range(rounds):
            turns["rev"].append(turn(old, ticks, loop_s, cpu))
            turns["this"].append(turn(ROOT, ticks, loop_s, cpu))
    med = {k: {f: float(np.median([t[f] for t, _ in ts])) for f in figures}
           for k, ts in turns.items()}
    pinned = "" if cpu is None else f", the loop on CPU {cpu} (its helpers off it)"
    what = (f"loop bench (service against the emulated rig, real-time{pinned}), {loop_s:g} s "
            "per case" if loop_s > 0 else
            f"ControlLoop.tick, default configuration, {ticks} ticks per figure")
    lines = [f"{what}, medians of {rounds} alternating turns (fresh process each)",
             f"{'':32}{'this tree':>12}{commit[:10]:>12}{'ratio':>8}"]
    for f in figures:
        a, b = med["this"][f], med["rev"][f]
        unit = " [us]" if f.endswith("_us") else " [%]" if f.endswith("_pct") else ""
        lines.append(f"{f + unit:32}{a:12.{3 if unit == ' [%]' else 1}f}"
                     f"{b:12.{3 if unit == ' [%]' else 1}f}{a / b if b else float('nan'):8.2f}")
    if loop_s > 0:
        lines.append("per turn (this tree / REV): " + "; ".join(
            f"{f}: " + ", ".join(f"{t[f]:.1f}/{r[f]:.1f}"
                                 for (t, _), (r, _) in zip(turns["this"], turns["rev"],
                                                           strict=True))
            for f in figures if f.endswith("_us")))
        lines.extend(fault_lines(turns, commit))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.tick_compare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rev", help="the git revision to compare against")
    ap.add_argument("--rounds", type=int, default=5, help="turns of each tree (default 5)")
    ap.add_argument("--ticks", type=int, default=3000,
                    help="ticks per figure and turn (default 3000)")
    ap.add_argument("--loop", type=float, default=0.0, metavar="SECONDS",
                    help="turns of the loop bench instead, SECONDS per case (bare, rec+tel)")
    ap.add_argument("--cpu", type=int, default=None,
                    help="with --loop: pin the loop to this CPU, as deploy/rig.service does "
                         "(the bench's --cpu)")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.ticks < 100 or not args.loop >= 0.0:
        ap.error("--rounds at least 1, --ticks at least 100, --loop 0 or more seconds")
    try:
        print(compare(args.rev, args.rounds, args.ticks, args.loop, args.cpu))
    except (ValueError, RuntimeError) as exc:
        print(exc, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
