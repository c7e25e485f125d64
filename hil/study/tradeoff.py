"""Comfort / travel trade-off from the linear covariance analysis (thesis Fig. 2.2).

For the single-LQG model (the configured vehicle's on-ground model nearest the static
tire deflection: a layered bank's configured layer, ``controller.config.one_layer``) and
white road velocity at the nominal speed and roughness, :func:`tradeoff_grid` evaluates
``controller.analysis.closed_loop`` over a grid of (rho1, rho2) with rho3 and rho4
fixed: the stationary absorbed-power ratio (F(s)-filtered acceleration mean square,
closed loop / passive), rattlespace RMS ratio and tire deflection RMS ratio, for the
full-state LQ loop and the LQG loop (Kalman filter + measured human filter), with an
ideal force actuator (the thesis's design view, Fig. 2.2) and, for a few rho1 rows, on the
linearised rig loop (servo-hydraulics under the PI force loop, the gains designed for it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from controller.analysis import closed_loop, output_mean_squares
from controller.arrays import FloatArray
from controller.config import RigConfig, one_layer
from controller.design import design_models, measurement_noise_cov
from controller.human_filter import human_filter
from controller.kalman import steady_state_kalman
from controller.lq import lq_gain
from controller.plant import static_tire_deflection_m
from controller.road_noise import road_velocity_intensity

__all__ = ["TradeoffGrid", "tradeoff_grid"]


@dataclass(frozen=True)
class TradeoffGrid:
    """Ratios to passive, arrays of shape (len(rho1), len(rho2)); NaN = no stabilising
    LQ solution, inf = unstable closed loop."""

    rho1: FloatArray
    rho2: FloatArray
    rho3: float
    rho4: float
    model: str
    lq: dict[str, FloatArray]
    lqg: dict[str, FloatArray]
    #: the same on the linearised rig loop (servo-hydraulics under the PI force loop,
    #: compute delay; ``controller.analysis.rig_closed_loop``), rows ``rig_rho1`` only;
    #: empty when the design assumes an ideal force actuator
    rig_rho1: FloatArray = field(default_factory=lambda: np.zeros(0))
    rig_lq: dict[str, FloatArray] = field(default_factory=dict)
    rig_lqg: dict[str, FloatArray] = field(default_factory=dict)


def tradeoff_grid(cfg: RigConfig, rho1: Sequence[float], rho2: Sequence[float],
                  rho3: float = 1e-8, rho4: float = 1.0, with_lqg: bool = True,
                  rig_rho1: Sequence[float] = ()) -> TradeoffGrid:
    hf = human_filter(cfg.design, cfg.sample_time_s)
    W = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    R = measurement_noise_cov(cfg)
    x2s = static_tire_deflection_m(cfg)
    mds = [md for md in design_models(one_layer(cfg)) if not md.model.airborne]
    md = min(mds, key=lambda m: abs(m.model.deflection_m - x2s))
    model = md.model
    kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W, R)
    extra = {"Phi": md.dfm.Phi, "Gamma_u": md.dfm.Gamma_u, "L": kf.L, "R": R}
    passive = output_mean_squares(closed_loop("passive", model, hf, np.zeros(6), W, **extra))
    r1, r2 = np.asarray(rho1, dtype=float), np.asarray(rho2, dtype=float)
    names = ("absorbed_power", "rattlespace_rms", "tire_deflection_rms")
    kinds: tuple[Literal["lq", "lqg"], ...] = ("lq", "lqg") if with_lqg else ("lq",)
    out = {k: {n: np.full((r1.size, r2.size), np.nan) for n in names} for k in kinds}
    for i, a in enumerate(r1):
        for j, b in enumerate(r2):
            try:
                K = lq_gain(model, hf, (a, b, rho3, rho4))
            except ValueError:
                continue
            for kind in kinds:
                ms = output_mean_squares(closed_loop(kind, model, hf, K, W, **extra))
                ratio = ms / passive
                out[kind]["absorbed_power"][i, j] = ratio[0]
                out[kind]["rattlespace_rms"][i, j] = np.sqrt(ratio[1])
                out[kind]["tire_deflection_rms"][i, j] = np.sqrt(ratio[2])
    rr1 = np.asarray(rig_rho1, dtype=float)
    rig: dict[str, dict[str, FloatArray]] = {}
    if rr1.size and getattr(cfg.design, "actuator_model", "ideal") == "hydraulic":
        from controller.analysis import rig_closed_loop
        delay = int(getattr(cfg.design, "compute_delay_ticks", 0))
        rig = {k: {n: np.full((rr1.size, r2.size), np.nan) for n in names}
               for k in ("lq", "lqg")}
        for i, a in enumerate(rr1):
            for j, b in enumerate(r2):
                for kind in ("lq", "lqg"):
                    try:
                        cl = rig_closed_loop(cfg, md, [a, b, rho3, rho4], kind, delay)
                    except ValueError:
                        continue
                    ratio = output_mean_squares(cl)[:3] / passive[:3]
                    rig[kind]["absorbed_power"][i, j] = ratio[0]
                    rig[kind]["rattlespace_rms"][i, j] = np.sqrt(ratio[1])
                    rig[kind]["tire_deflection_rms"][i, j] = np.sqrt(ratio[2])
    return TradeoffGrid(r1, r2, float(rho3), float(rho4), model.name, out["lq"],
                        out.get("lqg", {}), rr1 if rig else np.zeros(0),
                        rig.get("lq", {}), rig.get("lqg", {}))
