"""Linear closed-loop covariance analysis (white road velocity, thesis Ch. V in spirit).

For each on-ground model j the *plant* is that linear model (deviations from its static
equilibrium, gravity cancels) augmented with the human-body filter F(s) as the
performance output, driven by white road velocity of intensity W (nominal speed and
roughness).  Three loops, all exact on the sample grid (ZOH force, Van Loan noise):

- passive: u = 0;
- LQ: u_k = -K z_k with the true augmented state z = [x; xf];
- LQG: the model's steady-state Kalman filter (nominal noise entry) and the runtime's
  discrete human filter driven by the *measured* acceleration, ideal actuator (force =
  commanded force).  Timing as on the rig: the sensors at tick k see the force of the
  previous tick, y_k = C x_k + D u_{k-1} + v_k (load cell measures u_{k-1}); the filter
  update uses that force, the propagation uses the new command u_k, which then acts
  during [k, k+1).

With ``design.actuator_model = "hydraulic"`` (default) :func:`analyze` evaluates the
gains on the loop they are designed for (docs/design.md section 7): the linearised rig
of :mod:`controller.margins` -- servo-hydraulics under the PI force loop (kp and ki)
with its valve flow feedforward on the noisy LVDT reading, accelerometer low-pass,
load-cell noise, ``design.compute_delay_ticks`` ticks between the PI and the valve;
LQ = true plant and actuator state fed back, LQG = the runtime controller (Kalman
filter, human filter, spool model).

Stationary covariances come from the discrete Lyapunov equation.  The figures are the
mean squares at the sample instants of: y_f = Cf xf (F(s)-filtered sprung acceleration,
whose mean square is proportional to absorbed power; the filter input includes the
instantaneous u/M), rattlespace x1 - x2 and tire deflection x2; ratios are closed loop
over passive.  ``sprung_accel_rms_ratio`` is the unfiltered acceleration just after the
force update, a_k = A[2] x_k + u_k / M.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import control
import numpy as np
import scipy.linalg

from controller.actuator import flow_feedforward
from controller.arrays import FloatArray
from controller.config import RigConfig
from controller.design import ModelDesign, design_models, measurement_noise_cov
from controller.human_filter import HumanFilter, discretize_zoh, human_filter
from controller.kalman import process_noise_cov, steady_state_kalman
from controller.lq import augmented_plant, lq_gain
from controller.plant import LinearModel
from controller.road_noise import road_velocity_intensity

if TYPE_CHECKING:
    from controller.margins import LoopParts

__all__ = [
    "OUTPUTS",
    "ClosedLoop",
    "LoopKind",
    "analyze",
    "closed_loop",
    "output_mean_squares",
    "rig_closed_loop",
]

LoopKind = Literal["passive", "lq", "lqg"]

#: Performance outputs, in row order of ClosedLoop.Co.
OUTPUTS = ("filtered_accel", "rattlespace", "tire_deflection", "sprung_accel")


@dataclass(frozen=True)
class ClosedLoop:
    """xi+ = A xi + Bw w + Bv v,  o = Co xi + Dv v;  cov(w) = Qw, cov(v) = Rv (white)."""

    A: FloatArray
    Bw: FloatArray
    Bv: FloatArray
    Co: FloatArray
    Dv: FloatArray
    Qw: FloatArray
    Rv: FloatArray

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))


def closed_loop(kind: LoopKind, model: LinearModel, hf: HumanFilter, K: FloatArray,
                W: float, *, Phi: FloatArray | None = None, Gamma_u: FloatArray | None = None,
                L: FloatArray | None = None, R: FloatArray | None = None) -> ClosedLoop:
    """Closed loop of ``kind`` on the linear plant ``model`` (deviation coordinates).

    LQG needs the filter's Phi, Gamma_u (model of the filter), L and R.
    """
    dt = hf.dt_s
    aug = augmented_plant(model, hf, (0.0, 0.0, 1.0, 0.0))  # dynamics only
    Pa, Ga = discretize_zoh(aug.A, aug.B, dt)
    Qw = process_noise_cov(aug.A, aug.B1, W, dt)
    a_row = np.concatenate([model.A[2], np.zeros(2)])  # a = a_row z + u / M
    inv_m = aug.inv_mass
    Co_z = np.zeros((4, 6))
    Co_z[0, 4:] = hf.Cf
    Co_z[1, :2] = [1.0, -1.0]
    Co_z[2, 1] = 1.0
    Co_z[3] = a_row
    Rv = np.zeros((2, 2)) if R is None else R
    if kind in ("passive", "lq"):
        Kz = np.zeros(6) if kind == "passive" else K
        A = Pa - np.outer(Ga, Kz)
        Co = Co_z.copy()
        Co[3] -= inv_m * Kz
        return ClosedLoop(A, np.eye(6), np.zeros((6, 2)), Co, np.zeros((4, 2)), Qw, Rv)
    if Phi is None or Gamma_u is None or L is None or R is None:
        raise ValueError("LQG loop needs Phi, Gamma_u, L and R")
    # xi = [z (6), x_prior (4), xf_ctrl (2), u_prev (1)]
    n = 13
    iz, im, ic, iu = slice(0, 6), slice(6, 10), slice(10, 12), 12
    Cm = model.C_meas
    D = model.D_meas
    Kx, Kf = K[:4], K[4:]
    # x+ = xm + L (Cm (x - xm) + v);  u = -Kx x+ - Kf xc   -> u = ku xi + kv v
    xpost = np.zeros((4, n))
    xpost[:, :4] = L @ Cm
    xpost[:, im] = np.eye(4) - L @ Cm
    xpost_v = L
    ku = -Kx @ xpost
    ku[ic] -= Kf
    kv = -Kx @ xpost_v
    A = np.zeros((n, n))
    Bv = np.zeros((n, 2))
    A[iz, iz] = Pa
    A[iz] += np.outer(Ga, ku)
    Bv[iz] += np.outer(Ga, kv)
    A[im] = Phi @ xpost + np.outer(Gamma_u, ku)
    Bv[im] = Phi @ xpost_v + np.outer(Gamma_u, kv)
    # controller's human filter, driven by the measured acceleration (sees u_{k-1})
    a_meas = np.zeros(n)
    a_meas[:4] = Cm[1]
    a_meas[iu] = D[1]
    A[ic, ic] = hf.Ad
    A[ic] += np.outer(hf.Bd, a_meas)
    Bv[ic, 1] += hf.Bd
    A[iu] = ku
    Bv[iu] = kv
    Bw = np.zeros((n, 6))
    Bw[iz] = np.eye(6)
    Co = np.zeros((4, n))
    Co[:, iz] = Co_z
    Co[3] += inv_m * ku
    Dv = np.zeros((4, 2))
    Dv[3] = inv_m * kv
    return ClosedLoop(A, Bw, Bv, Co, Dv, Qw, Rv)


def rig_closed_loop(cfg: RigConfig, md: ModelDesign, weights: list[float],
                    kind: Literal["lq", "lqg"], delay_ticks: int,
                    parts: LoopParts | None = None) -> ClosedLoop:
    """LQ or LQG loop of model j on the linearised rig (:mod:`controller.margins`), with
    road noise (Van Loan), rattlespace / accelerometer / load-cell noise, and
    ``delay_ticks`` between the PI and the valve.  Outputs as :data:`OUTPUTS` (the last
    is the sampled true acceleration).  ``parts``: the loop's gains if the caller has
    them (default :func:`controller.margins.loop_parts` of ``weights``)."""
    from controller import margins as mg

    dt = cfg.sample_time_s
    if parts is None:
        parts = mg.loop_parts(cfg, md, weights)
    plant, Qw = mg.rig_plant_ss(md, cfg, "hydraulic", noise=True)
    n = Qw.shape[0]
    close = control.ss([], [], [], [[1.0]], dt, inputs=["fref_out"], outputs=["fref"],
                       name="close")
    blocks = [plant, mg.accel_sensor_ss(cfg, noise=True),
              mg.force_loop_ss(cfg.force_loop, flow_feedforward(cfg), dt),
              mg.delay_ss(delay_ticks, dt, "s_pi", "s"), close]
    if kind == "lqg":
        blocks.append(mg.runtime_controller_ss(md, parts, dt))
    elif kind == "lq":
        blocks.append(mg.fullstate_controller_ss(parts, n, dt))
    else:
        raise ValueError(f"kind {kind!r}: allowed 'lq', 'lqg'")
    w_in = [f"w{i}" for i in range(n)]
    sys = mg.connect(blocks, [*w_in, "v_r", "v_a", "v_F"], ["yf", "rattle", "tire", "a_true"])
    if np.any(sys.D[:, :n] != 0.0):
        raise AssertionError("road noise must not feed through to the outputs")
    noise = cfg.noise
    Rv = np.diag([noise.rattlespace_std_m**2, noise.accel_std_mps2**2, noise.force_std_n**2])
    return ClosedLoop(np.asarray(sys.A), np.asarray(sys.B[:, :n]), np.asarray(sys.B[:, n:]),
                      np.asarray(sys.C), np.asarray(sys.D[:, n:]), Qw, Rv)


def output_mean_squares(cl: ClosedLoop) -> FloatArray:
    """Stationary mean squares of the outputs (discrete Lyapunov); inf if unstable."""
    if not cl.spectral_radius < 1.0:
        return np.full(cl.Co.shape[0], np.inf)
    Q = cl.Bw @ cl.Qw @ cl.Bw.T + cl.Bv @ cl.Rv @ cl.Bv.T
    Sigma = scipy.linalg.solve_discrete_lyapunov(cl.A, 0.5 * (Q + Q.T))
    out = cl.Co @ Sigma @ cl.Co.T + cl.Dv @ cl.Rv @ cl.Dv.T
    return np.diag(out).copy()


def analyze(cfg: RigConfig, weight_set: int) -> dict[str, dict[str, dict[str, float]]]:
    """Ratios closed loop / passive per on-ground model, for "lq" and "lqg".

    ``weight_set`` is 1-based into cfg.design.weight_sets.  Returns
    {model_name: {"lq": {...}, "lqg": {...}, "passive_rms": {...}}}.
    """
    sets = cfg.design.weight_sets
    if not 1 <= weight_set <= len(sets):
        raise ValueError(f"weight set {weight_set}: allowed 1..{len(sets)}")
    weights = sets[weight_set - 1]
    hf = human_filter(cfg.design, cfg.sample_time_s)
    W = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    R = measurement_noise_cov(cfg)
    result: dict[str, dict[str, dict[str, float]]] = {}
    for md in design_models(cfg):
        model = md.model
        if model.airborne:
            continue
        K = lq_gain(model, hf, weights)
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W, R)
        ms = {kind: output_mean_squares(
            closed_loop(kind, model, hf, K, W, Phi=md.dfm.Phi, Gamma_u=md.dfm.Gamma_u,
                        L=kf.L, R=R))
            for kind in ("passive", "lq", "lqg")}
        if cfg.design.actuator_model == "hydraulic":
            d = cfg.design.compute_delay_ticks
            ms["lq"] = output_mean_squares(rig_closed_loop(cfg, md, list(weights), "lq", d))
            ms["lqg"] = output_mean_squares(rig_closed_loop(cfg, md, list(weights), "lqg", d))
        entry: dict[str, dict[str, float]] = {
            "passive_rms": {name: float(np.sqrt(v)) for name, v in zip(OUTPUTS, ms["passive"],
                                                                       strict=True)}}
        for kind in ("lq", "lqg"):
            r = ms[kind] / ms["passive"]
            entry[kind] = {
                "absorbed_power_ratio": float(r[0]),
                "rattlespace_rms_ratio": float(np.sqrt(r[1])),
                "tire_deflection_rms_ratio": float(np.sqrt(r[2])),
                "sprung_accel_rms_ratio": float(np.sqrt(r[3])),
            }
        result[model.name] = entry
    return result
