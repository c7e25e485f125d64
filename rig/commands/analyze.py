"""``rig analyze``: linear closed-loop covariance analysis against passive."""

from __future__ import annotations

import argparse

from controller.analysis import analyze
from controller.config import load_config
from rig import argtypes, strict_json

_KEYS = ("absorbed_power_ratio", "rattlespace_rms_ratio", "tire_deflection_rms_ratio")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    argtypes.add_weights_option(parser, None)
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    w = cfg.design.weight_set if args.weights is None else args.weights
    ws = cfg.design.single_gain_weight_set(w)       # 0, the travel schedule: its comfort set
    result = analyze(cfg, ws)
    if args.json:
        out = {name: {kind: {k: entry[kind][k] for k in _KEYS} for kind in ("lq", "lqg")}
               for name, entry in result.items()}
        print(strict_json.dumps({"weight_set": w, "analysed_weight_set": ws,
                                 "weights": cfg.design.weight_sets[ws - 1], "models": out}))
        return 0
    if w == 0:
        print(f"weight set 0 is the travel schedule: the linear analysis takes its comfort "
              f"set {ws}, the law where travel allows")
    print(f"weight set {ws}: rho = {cfg.design.weight_sets[ws - 1]} "
          f"(closed loop / passive, white road velocity at "
          f"{cfg.noise.nominal_speed_mps:g} m/s, Gd = {cfg.noise.nominal_roughness_gd:g} m^3)")
    width = max([12, *map(len, result)])     # layered names are longer
    print(f"{'model':{width}s} {'loop':5s} {'absorbed power':>15s} {'rattlespace rms':>16s} "
          f"{'tire defl. rms':>15s}")
    for name, entry in result.items():
        for kind in ("lq", "lqg"):
            r = entry[kind]
            print(f"{name:{width}s} {kind:5s} {r[_KEYS[0]]:15.4f} {r[_KEYS[1]]:16.4f} "
                  f"{r[_KEYS[2]]:15.4f}")
    return 0
