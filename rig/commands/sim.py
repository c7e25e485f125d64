"""``rig sim``: fast offline closed-loop simulation against the emulated rig.

    rig sim --road rough-course --speed 11.176 --duration 20 --controller fuzzy --weights 1
    rig sim --controller all --json          # every controller, one table / JSON object
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import load_config
from hil.sim.closed_loop import CONTROLLERS, SimResult, simulate
from hil.sim.roads import ROAD_NAMES, make_road
from rig import argtypes, strict_json
from rig.terminal import refuse

#: longest loop delay simulated (a second at 1 kHz)
MAX_DELAY_TICKS = 1000

TABLE_METRICS = (
    ("absorbed_power", "absorbed", "{:.4g}"),
    ("accel_rms_mps2", "acc_rms", "{:.3f}"),
    ("wk_rms_mps2", "wk_rms", "{:.3f}"),
    ("rattlespace_rms_m", "rs_rms_mm", "{:.2f}"),
    ("rattlespace_peak_m", "rs_pk_mm", "{:.1f}"),
    ("tire_load_rms_ratio", "tire_dyn", "{:.3f}"),
    ("time_off_ground_fraction", "off_gnd", "{:.3f}"),
    ("bump_stop_time_s", "stop_s", "{:.3f}"),
    ("force_rms_n", "F_rms_N", "{:.0f}"),
    ("hydraulic_power_mean_w", "hyd_W", "{:.0f}"),
    ("n_faults", "faults", "{:.0f}"),
    ("unstable", "unstable", "{:.0f}"),
    ("realtime_factor", "x_rt", "{:.0f}"),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--road", default="rough-course", type=argtypes.road,
                   help=f"road name: {', '.join(ROAD_NAMES)} (default rough-course)")
    p.add_argument("--speed", type=argtypes.config_real("noise.nominal_speed_mps", "m/s"),
                   default=11.176, help="m/s (default 25 mph)")
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_OFFLINE_S, "s",
                                                    lo_open=True),
                   default=20.0, help=f"s (default 20, at most {argtypes.MAX_OFFLINE_S:g})")
    argtypes.add_observe_option(p)
    argtypes.add_controller_option(p, CONTROLLERS, "fuzzy", extra=("all",))
    argtypes.add_weights_option(p, None)
    p.add_argument("--seed", type=argtypes.seed, default=1, help="road and sensor-noise seed")
    p.add_argument("--delay", type=argtypes.integer(0, MAX_DELAY_TICKS, "ticks"), default=0,
                   metavar="TICKS", help=f"loop delay (0..{MAX_DELAY_TICKS})")
    p.add_argument("--rate", type=argtypes.config_real("design.sample_rate_hz", "Hz"),
                   default=None, metavar="HZ",
                   help="controller sample rate (default: design.sample_rate_hz)")
    p.add_argument("--json", action="store_true",
                   help="print metrics as strict JSON (null for a non-finite value)")
    p.add_argument("--traces", metavar="NPZ", default=None, type=argtypes.output_file,
                   help="save traces (.npz); an existing file only with --force")
    p.add_argument("--force", action="store_true", help="replace the --traces file")


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
    road = make_road(args.road, args.speed, args.observe + args.duration, cfg.sample_time_s,
                     args.seed)
    names = list(CONTROLLERS) if args.controller == "all" else [args.controller]
    try:
        weights = cfg.design.weight_set if args.weights is None else args.weights
        results = [simulate(cfg, road, c, weights, delay_ticks=args.delay,
                            seed=args.seed, observe_s=args.observe) for c in names]
    except ValueError as exc:
        refuse("sim", f"{exc}")
        return 2
    if args.traces:
        arrays: dict[str, Any] = {f"{r.controller}.{k}": v for r in results
                                  for k, v in r.traces.items()}
        with Path(args.traces).open("wb") as fh:   # the name as given (no ".npz" added)
            np.savez_compressed(fh, **arrays)
    if args.json:
        out = {r.controller: r.metrics for r in results}
        print(strict_json.dumps(out if len(results) > 1 else results[0].metrics, indent=1))
    else:
        observed = (f" (observed {args.observe:g} s, armed {args.duration:g} s)"
                    if args.observe else "")
        print(f"road {road.name} at {road.speed_mps:g} m/s for {road.duration_s:g} s"
              f"{observed}, seed {args.seed}, delay {args.delay} ticks, "
              f"{1 / cfg.sample_time_s:g} Hz")
        print(format_table(results))
    return 1 if any(r.metrics["unstable"] for r in results) else 0
