"""Offline design of the controller bank -> :class:`controller.artifact.Design`.

For every model j of :func:`controller.plant.model_family` (deflection grid x tire
damping scales, then the airborne model):
- the ZOH discretisation of the absolute-coordinate filter model (Phi, Gamma_u, Gamma_g),
- a steady-state Kalman filter for every (speed, roughness) entry of the noise table
  (with random-walk measurement-bias states: their gains in ``bias_gain``),
- an LQ gain on the augmented plant (plant + human filter, and with
  ``design.actuator_model = "hydraulic"`` the force path of :mod:`controller.actuator`)
  for every weight set,
plus the discretised human-body filter, the tabulated fuzzy firing-weight curve and the
bump-stop law the filters take as a known input.
Derivations: docs/design.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from controller.actuator import ServoModel, servo_model
from controller.arrays import FloatArray
from controller.artifact import Design, build_metadata
from controller.config import RigConfig, layer_config, layer_grid
from controller.fuzzy import firing_weight_curve
from controller.human_filter import HumanFilter, human_filter
from controller.kalman import (
    DiscreteFilterModel,
    FilterModel,
    discretize_filter_model,
    filter_model,
    fused_prior_update,
    steady_state_kalman_stack,
)
from controller.lq import LQStackError, actuated_lq_problem, dlqr_cross_stack, lq_problem
from controller.plant import LinearModel, model_family
from controller.road_noise import noise_table_entries

__all__ = ["FUZZY_GRID_POINTS", "ModelDesign", "bump_stop_input", "design_bank",
           "design_models", "layer_config", "measurement_noise_cov"]


#: Points of the tabulated firing-weight curve over the universe of q.
FUZZY_GRID_POINTS = 2001


@dataclass(frozen=True)
class ModelDesign:
    """Intermediate per-model results (used by the design, the analysis and the CLI)."""

    model: LinearModel
    fm: FilterModel
    dfm: DiscreteFilterModel


def measurement_noise_cov(cfg: RigConfig) -> FloatArray:
    """R = diag(rattlespace_std^2, accel_std^2) [m^2, (m/s^2)^2] per sample."""
    return np.diag([cfg.noise.rattlespace_std_m**2, cfg.noise.accel_std_mps2**2])


def bump_stop_input(cfg: RigConfig) -> FloatArray:
    """[stiffness N/m, rebound-stop LVDT reading m, compression-stop LVDT reading m] of the
    bump-stop force the filters take as a known input (stiffness 0: no stop input)."""
    d, v = cfg.design, cfg.vehicle
    k = v.bump_stop_stiffness_n_per_m if d.bump_stop_filter_input else 0.0
    c = d.bump_stop_centre_lvdt_m
    return np.array([k, c - v.rattlespace_travel_m, c + v.rattlespace_travel_m])


def _layer_suffix(cfg: RigConfig, scales: tuple[float, float, float, float]) -> str:
    d = cfg.design
    m, k, c, t = scales
    return (f"_M{m:g}" + (f"_K{k:g}" if len(d.spring_rate_scales) > 1 else "")
            + (f"_C{c:g}" if len(d.damping_scales) > 1 else "")
            + (f"_T{t:g}" if len(d.tire_stiffness_scales) > 1 else ""))


def _model_design(model: LinearModel, cfg: RigConfig) -> ModelDesign:
    fm = filter_model(model, cfg)
    return ModelDesign(model, fm, discretize_filter_model(fm, cfg.sample_time_s))


def design_models(cfg: RigConfig) -> list[ModelDesign]:
    """The bank's models: the tire family of :func:`controller.plant.model_family` once per
    layer (:func:`layer_grid`, layer major; with more than one layer the names carry
    ``_M<scale>``, and ``_K<scale>`` / ``_C<scale>`` / ``_T<scale>`` where those axes have
    more than one value), then the airborne model (configured vehicle)."""
    layers = layer_grid(cfg)
    if layers == [(1.0, 1.0, 1.0, 1.0)]:
        return [_model_design(model, cfg) for model in model_family(cfg)]
    out = []
    for scales in layers:
        cfg_l = layer_config(cfg, *scales)
        suffix = _layer_suffix(cfg, scales)
        out += [_model_design(dataclasses.replace(model, name=f"{model.name}{suffix}"),
                              cfg_l)
                for model in model_family(cfg_l) if not model.airborne]
    out += [_model_design(model, cfg) for model in model_family(cfg) if model.airborne]
    return out


def _grid_index(cfg: RigConfig, j: int, airborne: bool) -> tuple[int, int]:
    """(deflection, damping scale) index of model j within its layer."""
    if airborne:
        return (-1, -1)
    n_scale = len(cfg.design.tire_damping_scales)
    j %= n_scale * len(cfg.design.linearisation_deflections_m)
    return (j // n_scale, j % n_scale)


def _lq_gains(cfg: RigConfig, mds: list[ModelDesign], hf: HumanFilter, servo: ServoModel,
              gains: FloatArray, act_gains: FloatArray) -> None:
    """Fill ``gains`` (W, J, 6) and ``act_gains`` (W, J, 3 + D) with every on-ground
    model's LQ gain for every weight set, the DAREs solved as one stack
    (:func:`controller.lq.dlqr_cross_stack`: the numbers of :func:`actuated_lq_gain` /
    :func:`lq_gain` model by model); the airborne model keeps 0.  Raises ValueError
    naming the model and weight set whose DARE has no stabilising solution."""
    hydraulic = cfg.design.actuator_model == "hydraulic"
    cases = [(w, j) for j, md in enumerate(mds) if not md.model.airborne
             for w in range(len(cfg.design.weight_sets))]
    if not cases:
        return
    probs = [actuated_lq_problem(mds[j].model, hf, cfg.design.weight_sets[w], servo)
             if hydraulic else lq_problem(mds[j].model, hf, cfg.design.weight_sets[w])
             for w, j in cases]
    try:
        K, _ = dlqr_cross_stack(np.stack([p.Ad for p in probs]),
                                np.stack([p.Bd for p in probs]),
                                np.stack([p.Qd for p in probs]),
                                np.array([p.Rd for p in probs]),
                                np.stack([p.Nd for p in probs]))
    except LQStackError as exc:
        w, j = cases[exc.index]
        raise ValueError(f"model {mds[j].model.name}, weight set {w + 1}: {exc.reason}"
                         ) from exc
    for (w, j), k in zip(cases, K, strict=True):
        gains[w, j] = k[:6]
        if hydraulic:
            act_gains[w, j] = k[6:]


def design_bank(cfg: RigConfig, *, fuzzy_points: int = FUZZY_GRID_POINTS) -> Design:
    """Design every filter and gain of the bank for ``cfg`` (raises ValueError if a
    Riccati equation has no stabilising solution)."""
    dt = cfg.sample_time_s
    g = cfg.vehicle.gravity_mps2
    hf: HumanFilter = human_filter(cfg.design, dt)
    mds = design_models(cfg)
    J = len(mds)
    entries = noise_table_entries(cfg.noise)
    S = len(entries)
    W = len(cfg.design.weight_sets)
    R = measurement_noise_cov(cfg)

    bias_qd = np.array([cfg.design.filter_rattlespace_bias_drift ** 2,
                        cfg.design.filter_accel_bias_drift ** 2]) * dt
    kalman_gain = np.zeros((J, S, 4, 2))
    bias_gain = np.zeros((J, S, 2, 2))
    f_cov = np.zeros((J, S, 2, 2))
    f_inv = np.zeros((J, S, 2, 2))
    f_logdet = np.zeros((J, S))
    fA = np.zeros((J, S, 4, 4))
    fBy = np.zeros((J, S, 4, 2))
    fBu = np.zeros((J, S, 4))
    fb = np.zeros((J, S, 4))
    servo = servo_model(cfg)
    gains = np.zeros((W, J, 6))
    act_gains = np.zeros((W, J, 3 + servo.delay_ticks))
    eq = np.full((J, 4), np.nan)
    w_ints = np.array([w_int for _v, _gd, w_int in entries])
    for j, md in enumerate(mds):
        if md.model.equilibrium is not None:
            eq[j] = md.model.equilibrium
        try:
            kf = steady_state_kalman_stack(
                np.broadcast_to(md.dfm.Phi, (S, 4, 4)), np.broadcast_to(md.fm.C, (S, 2, 4)),
                md.dfm.Qd_unit * w_ints[:, None, None] + md.dfm.Qd_fixed, R, bias_qd)
        except ValueError as exc:
            raise ValueError(f"model {md.model.name}: {exc}") from exc
        kalman_gain[j], bias_gain[j], f_cov[j], f_inv[j] = kf.L, kf.L_bias, kf.F, kf.F_inv
        f_logdet[j] = kf.logdet
        for s in range(S):
            fused = fused_prior_update(md.dfm.Phi, md.dfm.Gamma_u, md.dfm.Gamma_g, g,
                                       md.fm.C, md.fm.D, md.fm.y_offset, kalman_gain[j, s])
            fA[j, s], fBy[j, s], fBu[j, s], fb[j, s] = fused.A, fused.By, fused.Bu, fused.b
    _lq_gains(cfg, mds, hf, servo, gains, act_gains)

    q_grid, w_curve = firing_weight_curve(cfg.fuzzy, fuzzy_points)
    v = cfg.vehicle
    design = Design(
        dt_s=dt,
        model_names=np.array([md.model.name for md in mds], dtype=np.str_),
        airborne=np.array([md.model.airborne for md in mds], dtype=bool),
        grid_index=np.array([_grid_index(cfg, j, md.model.airborne)
                             for j, md in enumerate(mds)], dtype=np.int64).reshape(J, 2),
        equilibrium=eq,
        Phi=np.stack([md.dfm.Phi for md in mds]),
        Gamma_u=np.stack([md.dfm.Gamma_u for md in mds]),
        Gamma_g=np.stack([md.dfm.Gamma_g for md in mds]),
        C_meas=np.stack([md.fm.C for md in mds]),
        D_meas=np.stack([md.fm.D for md in mds]),
        y_offset=np.array([0.0, -g]),
        kalman_gain=kalman_gain,
        bias_gain=bias_gain,
        innovation_cov=f_cov,
        innovation_cov_inv=f_inv,
        innovation_logdet=f_logdet,
        filter_A=fA,
        filter_By=fBy,
        filter_Bu=fBu,
        filter_b=fb,
        noise_speeds_mps=np.array(cfg.noise.speeds_mps, dtype=float),
        noise_roughness_gd=np.array(cfg.noise.road_roughness_gd, dtype=float),
        lq_gain=gains,
        actuator_gain=act_gains,
        servo_model=servo.as_array(),
        human_filter_Ad=hf.Ad.copy(),
        human_filter_Bd=hf.Bd.copy(),
        human_filter_Cd=hf.Cd.copy(),
        fuzzy_q_grid=q_grid,
        fuzzy_weight_curve=w_curve,
        static_rattlespace_m=v.sprung_mass_kg * g / v.suspension_stiffness_n_per_m,
        bump_stop=bump_stop_input(cfg),
        metadata=build_metadata(cfg),
    )
    design.validate()
    return design
