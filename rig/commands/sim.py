"""``rig sim``: fast offline closed-loop simulation against the emulated rig.

    rig sim --road rough-course --speed 11.176 --duration 20 --controller fuzzy --weights 1
    rig sim --controller all --json          # every controller, one table / JSON object
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import load_config
from hil.roads import ROAD_NAMES, RoadError, make_road
from hil.sim import CONTROLLERS, SimResult, simulate

TABLE_METRICS = (
    ("absorbed_power", "absorbed", "{:.4g}"),
    ("accel_rms_mps2", "acc_rms", "{:.3f}"),
    ("wk_rms_mps2", "wk_rms", "{:.3f}"),
    ("rattlespace_rms_m", "rs_rms_mm", "{:.2f}"),
    ("rattlespace_peak_m", "rs_pk_mm", "{:.1f}"),
    ("tire_load_rms_ratio", "tire_dyn", "{:.3f}"),
    ("time_off_ground_fraction", "off_gnd", "{:.3f}"),
    ("force_rms_n", "F_rms_N", "{:.0f}"),
    ("hydraulic_power_mean_w", "hyd_W", "{:.0f}"),
    ("n_faults", "faults", "{:.0f}"),
    ("unstable", "unstable", "{:.0f}"),
    ("realtime_factor", "x_rt", "{:.0f}"),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--road", default="rough-course",
                   help=f"road name: {', '.join(ROAD_NAMES)} (default rough-course)")
    p.add_argument("--speed", type=float, default=11.176, help="m/s (default 25 mph)")
    p.add_argument("--duration", type=float, default=20.0, help="s (default 20)")
    p.add_argument("--controller", default="fuzzy", choices=(*CONTROLLERS, "all"))
    p.add_argument("--weights", type=int, default=1, help="weight set 1 or 2 (default 1)")
    p.add_argument("--seed", type=int, default=1, help="road and sensor-noise seed")
    p.add_argument("--delay", type=int, default=0, metavar="TICKS", help="loop delay")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="controller sample rate (default: design.sample_rate_hz)")
    p.add_argument("--json", action="store_true", help="print metrics as JSON")
    p.add_argument("--traces", metavar="NPZ", default=None, help="save traces (.npz)")


def _row(res: SimResult) -> str:
    cells = []
    for key, _, fmt in TABLE_METRICS:
        v = res.metrics[key] * (1000.0 if key.startswith("rattlespace") else 1.0)
        cells.append(fmt.format(v))
    return f"{res.controller:<8} {res.weight_set:>2} " + " ".join(f"{c:>10}" for c in cells)


def format_table(results: list[SimResult]) -> str:
    head = f"{'ctrl':<8} {'w':>2} " + " ".join(f"{h:>10}" for _, h, _ in TABLE_METRICS)
    return "\n".join([head, *(_row(r) for r in results)])


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if args.rate is not None:
        cfg = cfg.replace(design={"sample_rate_hz": args.rate})
    if not 1 <= args.weights <= len(cfg.design.weight_sets):
        print(f"rig sim: --weights {args.weights}: allowed 1..{len(cfg.design.weight_sets)}",
              file=sys.stderr)
        return 2
    try:
        road = make_road(args.road, args.speed, args.duration, cfg.sample_time_s, args.seed)
    except RoadError as exc:
        print(f"rig sim: {exc}", file=sys.stderr)
        return 2
    names = list(CONTROLLERS) if args.controller == "all" else [args.controller]
    try:
        results = [simulate(cfg, road, c, args.weights, delay_ticks=args.delay,
                            seed=args.seed) for c in names]
    except ValueError as exc:
        print(f"rig sim: {exc}", file=sys.stderr)
        return 2
    if args.traces:
        arrays: dict[str, Any] = {f"{r.controller}.{k}": v for r in results
                                  for k, v in r.traces.items()}
        np.savez_compressed(Path(args.traces), **arrays)
    if args.json:
        out = {r.controller: r.metrics for r in results}
        print(json.dumps(out if len(results) > 1 else results[0].metrics, indent=1))
    else:
        print(f"road {road.name} at {road.speed_mps:g} m/s for {road.duration_s:g} s, "
              f"seed {args.seed}, delay {args.delay} ticks, {1 / cfg.sample_time_s:g} Hz")
        print(format_table(results))
    return 1 if any(r.metrics["unstable"] for r in results) else 0
