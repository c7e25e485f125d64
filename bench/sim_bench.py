"""Speed of the emulated rig: plant tick, sensors, and closed-loop offline simulation.

``run() -> list[dict]``: one row per item with the median over repeats: microseconds per
1 ms tick and the real-time factor (simulated seconds per wall-clock second) at 1 kHz
control.  The goal is >= 20x real time for every controller.  ``python -m bench.sim_bench``
prints the table (``--quick`` for a short run).
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path
from typing import Any

from bench.timing import median_call_ns
from controller.config import default_config
from hil.sim.closed_loop import CONTROLLERS, cached_design, simulate
from hil.sim.plant import RigPlant
from hil.sim.roads import make_road
from hil.sim.sensors import SensorSuite

ROOT = Path(__file__).resolve().parents[1]

NAME = "sim"
TITLE = "Emulated rig: per-tick cost and offline real-time factor at 1 kHz (median)"
GOAL_RT = 20.0


def _tick_us(fn: Any, n: int, repeats: int) -> float:
    return median_call_ns(fn, n, repeats) * 1e-3


def run(quick: bool = False) -> list[dict[str, Any]]:
    cfg = default_config()
    dt = cfg.sample_time_s
    n = 2000 if quick else 10000
    repeats = 3 if quick else 5
    plant = RigPlant(cfg)
    plant.advance(dt, 0.0, False, 0.0, 0.0)           # compile / load the kernel
    sensors = SensorSuite(cfg.sensors, cfg.noise, 1, dt_s=dt)
    rows: list[dict[str, Any]] = []
    us = _tick_us(lambda: plant.advance(dt, 0.1, False, 0.0, 0.0), n, repeats)
    rows.append({"item": f"plant.advance ({plant.substeps} RK4 substeps)", "us_per_tick": us,
                 "realtime_factor": dt * 1e6 / us})
    us = _tick_us(lambda: sensors.read(plant), n, repeats)
    rows.append({"item": "sensors.read", "us_per_tick": us,
                 "realtime_factor": dt * 1e6 / us})
    duration = 2.0 if quick else 10.0
    road = make_road("rough-course", 11.176, duration, dt, seed=1)
    cached_design(cfg)
    for c in CONTROLLERS:
        simulate(cfg, make_road("bump", 11.176, 0.05, dt), c)   # warm-up (numba)
        rts = [simulate(cfg, road, c, 1).metrics["realtime_factor"] for _ in range(repeats)]
        rt = statistics.median(rts)
        rows.append({"item": f"simulate {c} (rough course, {duration:g} s)",
                     "us_per_tick": 1e6 * dt / rt, "realtime_factor": rt})
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    lines = [TITLE, f"{'item':<44} {'us/tick':>9} {'x real time':>12} {'goal':>6}"]
    for r in rows:
        ok = "ok" if r["realtime_factor"] >= GOAL_RT else "SLOW"
        lines.append(f"{r['item']:<44} {r['us_per_tick']:>9.2f} {r['realtime_factor']:>12.1f} "
                     f"{ok:>6}")
    return "\n".join(lines)


if __name__ == "__main__":
    print(format_table(run(quick="--quick" in sys.argv)))
