"""Must-show figures of the identification (docs/identify.md): `python -m hil.study.identify_check`.

1. **Recovery and coverage.**  The emulated rig of ``[emulator]`` M x1.12, K x0.92,
   C x1.10, tire stiffness x0.90 (sensor noise as configured) runs the excitation of
   ``[excitation]`` in :func:`hil.sim.excitation_run.simulate_excitation` -- the recording
   content of ``rig demo --excite`` (same plant, sensors, CAN quantisation, force loop
   and one tick of loop delay), faster than real time -- for ``--repeats`` sensor-noise
   seeds; :func:`controller.identify.identify` on each.  Table: worst error of M, K, C,
   m and the tire coefficient and how many 95 % intervals contain the truth.
2. **Closing the loop.**  ``--plants`` Monte Carlo plants at ``--spread`` (draws of
   :func:`hil.sim.montecarlo.draw_params`); for each: identify it from an excitation run,
   design the bank from the identified configuration, from the plant's true parameters
   and from the nominal configuration, and run each bank (fuzzy, weight set 1) on that
   plant over the rough course (``--road-s`` s, same road and noise seeds).  Table: the
   absorbed power of each and the faults; the identified design must be within 10 % of
   the true design's absorbed power with no fault.

Prints the two tables (``--json``: as JSON).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from controller.config import RigConfig, default_config, parse_config
from controller.design import design_bank
from controller.identify import RunData, fitted_config, identify
from hil.sim.closed_loop import BankController, run_closed_loop
from hil.sim.excitation_run import simulate_excitation
from hil.sim.montecarlo import draw_params
from hil.sim.plant import PlantParams, emulated_params
from hil.sim.roads import make_road

__all__ = ["CHECK_EMULATOR", "closed_loop_check", "coverage_check", "main", "run_data_of"]

#: the emulated rig of the must-show figures
CHECK_EMULATOR = {"sprung_mass_scale": 1.12, "spring_rate_scale": 0.92,
                  "damping_scale": 1.10, "tire_stiffness_scale": 0.90}
_KEYS = ("vehicle.sprung_mass_kg", "vehicle.suspension_stiffness_n_per_m",
         "vehicle.suspension_damping_ns_per_m", "vehicle.unsprung_mass_kg",
         "tire.stiffness_coefficient")


def run_data_of(cfg: RigConfig, channels: dict[str, Any]) -> RunData:
    """:class:`RunData` of :func:`simulate_excitation`'s channels."""
    excite = channels["excitation"] > 0
    n_rest = round(cfg.excitation.rest_s / cfg.sample_time_s)
    rest = np.zeros_like(excite)
    rest[:n_rest] = True
    return RunData(cfg.sample_time_s, channels["rattlespace_m"],
                   channels["sprung_accel_mps2"], channels["force_meas_n"],
                   channels["force_ref_n"], channels["spool_cmd"], excite, rest)


def true_values(cfg: RigConfig, p: PlantParams) -> dict[str, float]:
    """The plant ``p``'s values under the config keys (tire law relative to ``cfg``)."""
    v, t = cfg.vehicle, cfg.tire
    return {"vehicle.sprung_mass_kg": p.sprung_mass_kg or v.sprung_mass_kg,
            "vehicle.unsprung_mass_kg": p.unsprung_mass_kg or v.unsprung_mass_kg,
            "vehicle.suspension_stiffness_n_per_m": (p.suspension_stiffness_n_per_m
                                                     or v.suspension_stiffness_n_per_m),
            "vehicle.suspension_damping_ns_per_m": (p.suspension_damping_ns_per_m
                                                    or v.suspension_damping_ns_per_m),
            "tire.stiffness_coefficient": t.stiffness_coefficient * p.tire_stiffness_scale}


def coverage_check(repeats: int = 20) -> dict[str, Any]:
    """Part 1 (see the module docstring)."""
    cfg = parse_config({"emulator": CHECK_EMULATOR})
    p = emulated_params(cfg)
    assert p is not None
    truth = true_values(cfg, p)
    errors: dict[str, list[float]] = {k: [] for k in _KEYS}
    covered = dict.fromkeys(_KEYS, 0)
    half: dict[str, list[float]] = {k: [] for k in _KEYS}
    for seed in range(1, repeats + 1):
        ident = identify(run_data_of(cfg, simulate_excitation(cfg, seed=seed)), cfg)
        for k in _KEYS:
            v, (lo, hi) = ident.estimates[k], ident.ci95[k]
            errors[k].append((v - truth[k]) / truth[k])
            covered[k] += int(lo <= truth[k] <= hi)
            half[k].append((hi - lo) / 2 / truth[k])
    return {"repeats": repeats, "truth": truth,
            "rows": {k: {"max_abs_error": float(np.max(np.abs(errors[k]))),
                         "mean_error": float(np.mean(errors[k])),
                         "mean_half_width": float(np.mean(half[k])),
                         "covered": covered[k]} for k in _KEYS}}


def _true_config(cfg: RigConfig, p: PlantParams) -> RigConfig:
    t = cfg.tire
    vals = true_values(cfg, p)
    return cfg.replace(
        vehicle={k.split(".")[1]: v for k, v in vals.items() if k.startswith("vehicle.")},
        tire={"stiffness_coefficient": vals["tire.stiffness_coefficient"],
              "damping_c2": t.damping_c2 * p.tire_damping_scale,
              "damping_c3": t.damping_c3 * p.tire_damping_scale})


def closed_loop_check(plants: int = 10, spread: float = 0.15, road_s: float = 20.0,
                      seed: int = 0) -> dict[str, Any]:
    """Part 2 (see the module docstring)."""
    cfg = default_config()
    road = make_road("rough-course", cfg.noise.nominal_speed_mps, road_s, cfg.sample_time_s,
                     seed=cfg.sensors.seed)
    nominal = design_bank(cfg)
    rows = []
    for i, p in enumerate(draw_params(cfg, plants, spread, seed=seed)):
        ident = identify(run_data_of(cfg, simulate_excitation(cfg, seed=100 + i, params=p)),
                         cfg)
        cfg_id = fitted_config(cfg, ident)
        cfg_true = _true_config(cfg, p)
        row: dict[str, Any] = {"plant": i, "truth": true_values(cfg, p),
                               "identified": {k: ident.estimates[k] for k in _KEYS}}
        for name, c, design in (("true", cfg_true, design_bank(cfg_true)),
                                ("identified", cfg_id, design_bank(cfg_id)),
                                ("nominal", cfg, nominal)):
            # the plant and the force loop from the rig's configuration + the drawn
            # parameters, the bank designed and run from ``c``
            ctrl = BankController(design, c, "fuzzy", 1, road)
            res = run_closed_loop(cfg, road, ctrl, params=p, seed=cfg.sensors.seed)
            row[name] = {"absorbed_power": res.metrics["absorbed_power"],
                         "faults": int(res.metrics["n_faults"]),
                         "unstable": bool(res.metrics["unstable"])}
        t = row["true"]["absorbed_power"]
        row["identified_vs_true"] = row["identified"]["absorbed_power"] / t - 1.0
        row["nominal_vs_true"] = row["nominal"]["absorbed_power"] / t - 1.0
        rows.append(row)
    ok = sum(abs(r["identified_vs_true"]) <= 0.10 and r["identified"]["faults"] == 0
             for r in rows)
    return {"plants": plants, "spread": spread, "road_s": road_s, "rows": rows,
            "identified_within_10pct_no_fault": ok,
            "nominal_within_10pct_no_fault": sum(
                abs(r["nominal_vs_true"]) <= 0.10 and r["nominal"]["faults"] == 0
                for r in rows),
            "nominal_faults": sum(r["nominal"]["faults"] > 0 for r in rows)}


def _print(cov: dict[str, Any] | None, loop: dict[str, Any] | None) -> None:
    if cov is not None:
        print(f"Recovery on the emulated rig M x1.12, K x0.92, C x1.10, tire stiffness x0.90 "
              f"({cov['repeats']} sensor-noise seeds, 20 s excitation):")
        print(f"{'parameter':40} {'truth':>10} {'max |err| %':>12} {'mean err %':>11} "
              f"{'CI +/- %':>9} {'CI covers':>10}")
        for k, r in cov["rows"].items():
            print(f"{k:40} {cov['truth'][k]:10.5g} {100 * r['max_abs_error']:12.3f} "
                  f"{100 * r['mean_error']:+11.3f} {100 * r['mean_half_width']:9.3f} "
                  f"{r['covered']:>6}/{cov['repeats']}")
    if loop is not None:
        print(f"\nClosing the loop: {loop['plants']} Monte Carlo plants at "
              f"{100 * loop['spread']:.0f} % spread, fuzzy bank (weight set 1), rough course "
              f"{loop['road_s']:g} s; absorbed power [(m/s2)^2] of the bank designed from:")
        print(f"{'plant':>5} {'true':>9} {'identified':>11} {'ident/true':>11} "
              f"{'nominal':>9} {'nom/true':>9} {'faults t/i/n':>13}")
        for r in loop["rows"]:
            f = "/".join(str(r[n]["faults"]) for n in ("true", "identified", "nominal"))
            print(f"{r['plant']:5d} {r['true']['absorbed_power']:9.5f} "
                  f"{r['identified']['absorbed_power']:11.5f} "
                  f"{100 * r['identified_vs_true']:+10.2f}% "
                  f"{r['nominal']['absorbed_power']:9.5f} {100 * r['nominal_vs_true']:+8.2f}% "
                  f"{f:>13}")
        print(f"identified design within 10 % of the true design, no fault: "
              f"{loop['identified_within_10pct_no_fault']}/{loop['plants']}; nominal design: "
              f"{loop['nominal_within_10pct_no_fault']}/{loop['plants']} "
              f"({loop['nominal_faults']} with a fault)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hil.study.identify_check",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--plants", type=int, default=10)
    ap.add_argument("--spread", type=float, default=0.15)
    ap.add_argument("--road-s", type=float, default=20.0)
    ap.add_argument("--only", choices=("coverage", "loop"), default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.plants < 1 or not (0.0 < args.spread <= 0.5) \
            or not (1.0 <= args.road_s <= 600.0) or not math.isfinite(args.spread):
        print("identify_check: --repeats/--plants >= 1, --spread in (0, 0.5], --road-s in "
              "[1, 600]", file=sys.stderr)
        return 2
    cov = coverage_check(args.repeats) if args.only in (None, "coverage") else None
    loop = (closed_loop_check(args.plants, args.spread, args.road_s)
            if args.only in (None, "loop") else None)
    if args.json:
        print(json.dumps({"coverage": cov, "closed_loop": loop}, default=float))
    else:
        _print(cov, loop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
