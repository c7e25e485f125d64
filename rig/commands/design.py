"""``rig design``: design the LQG bank and write the versioned artifact (.npz)."""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

from controller.analysis import rig_closed_loop
from controller.artifact import Design, save_design
from controller.config import RigConfig, load_config
from controller.design import design_models
from controller.human_filter import discretize_zoh, human_filter
from controller.lq import augmented_plant
from controller.margins import loop_kalman_gain, loop_parts
from controller.road_noise import nearest_noise_entry
from rig import argtypes, strict_json
from rig.design_cache import design_for
from rig.terminal import refuse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="FILE", type=argtypes.output_file,
                        help="artifact to write (.npz); an existing file only with --force")
    parser.add_argument("--force", action="store_true",
                        help="replace the --out file if it exists")
    parser.add_argument("--json", action="store_true",
                        help="print gains and closed-loop poles as strict JSON "
                             "(null for a non-finite value)")


def pole_info(z: complex, dt_s: float) -> dict[str, float]:
    """Discrete pole and its continuous equivalent s = ln(z)/dt (natural freq., damping)."""
    s = complex(np.log(complex(z))) / dt_s if z != 0 else complex(-math.inf)
    wn = abs(s)
    return {"re": float(np.real(z)), "im": float(np.imag(z)), "abs": float(abs(z)),
            "wn_rad_s": float(wn), "f_hz": float(wn / (2 * math.pi)),
            "zeta": float(-s.real / wn) if wn > 0 and math.isfinite(wn) else 1.0}


def _poles(mat: np.ndarray, dt_s: float) -> list[dict[str, float]]:
    ev = np.linalg.eigvals(mat)
    ev = ev[np.argsort(-np.abs(ev))]
    return [pole_info(complex(z), dt_s) for z in ev]


def design_summary(design: Design, cfg: RigConfig) -> dict[str, Any]:
    """Per model: LQ gains and closed-loop poles per weight set (of the whole rig loop and of
    the ideal-actuator design loop), nominal Kalman gain and
    filter poles."""
    dt = design.dt_s
    hf = human_filter(cfg.design, dt)
    s_nom = nearest_noise_entry(design.noise_speeds_mps, design.noise_roughness_gd,
                                cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    models: dict[str, Any] = {}
    for j, md in enumerate(design_models(cfg)):
        entry: dict[str, Any] = {"airborne": bool(design.airborne[j]), "lq": {}}
        aug = augmented_plant(md.model, hf, (0.0, 0.0, 1.0, 0.0))
        Pa, Ga = discretize_zoh(aug.A, aug.B, dt)
        # the rig loop's Kalman gain, once per model (the design's gains are loop_parts'
        # own, bit for bit)
        L = None if design.airborne[j] else loop_kalman_gain(cfg, md)
        for w in range(design.n_weight_sets):
            K = design.lq_gain[w, j]
            lq: dict[str, Any] = {
                "gain": K.tolist(),
                "actuator_gain": design.actuator_gain[w, j].tolist(),
                # the 6-state loop with an ideal force actuator (the thesis's design view)
                "ideal_actuator_closed_loop_poles": _poles(Pa - np.outer(Ga, K), dt),
            }
            if not design.airborne[j]:
                # the loop the rig really runs: LQG + PI force loop + servo-hydraulics +
                # the design's compute delay (controller.analysis.rig_closed_loop)
                parts = loop_parts(cfg, md, list(cfg.design.weight_sets[w]),
                                   gains=(K, design.actuator_gain[w, j]), kalman_gain=L)
                cl = rig_closed_loop(cfg, md, list(cfg.design.weight_sets[w]), "lqg",
                                     cfg.design.compute_delay_ticks, parts)
                lq["closed_loop_poles"] = _poles(cl.A, dt)
            entry["lq"][f"weight_set_{w + 1}"] = lq
        entry["kalman"] = {
            "noise_entry": s_nom,
            "speed_mps": float(design.noise_speeds_mps[s_nom // design.noise_roughness_gd.size]),
            "roughness_gd": float(design.noise_roughness_gd[s_nom
                                                            % design.noise_roughness_gd.size]),
            "gain": design.kalman_gain[j, s_nom].tolist(),
            "innovation_cov": design.innovation_cov[j, s_nom].tolist(),
            "filter_poles": _poles(design.filter_A[j, s_nom], dt),
        }
        models[str(design.model_names[j])] = entry
    return {"dt_s": dt, "config_hash": design.metadata["config_hash"], "models": models}


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    try:
        design = design_for(cfg)        # designed, or the same artifact from the cache
    except ValueError as exc:
        refuse("design", f"design failed: {exc}")
        return 1
    save_design(design, args.out)
    summary = design_summary(design, cfg)
    if args.json:
        print(strict_json.dumps(summary))
        return 0
    print(f"wrote {args.out}: {design.n_models} models, {design.n_noise} noise entries, "
          f"{design.n_weight_sets} weight sets, dt = {design.dt_s * 1e3:g} ms")
    width = max([12, *map(len, summary["models"])])     # layered names are longer
    for name, entry in summary["models"].items():
        radii = [max(p["abs"] for p in v.get("closed_loop_poles",
                                             v["ideal_actuator_closed_loop_poles"]))
                 for v in entry["lq"].values()]
        frad = max(p["abs"] for p in entry["kalman"]["filter_poles"])
        print(f"  {name:{width}s} closed-loop spectral radius "
              f"{', '.join(f'{r:.6f}' for r in radii)}; filter {frad:.6f}")
    return 0
