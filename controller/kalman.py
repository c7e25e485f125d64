"""Steady-state Kalman filters of the bank (thesis Ch. III, Eq. 3.3-3.8).

Each filter works in *absolute* coordinates (positions from the unloaded springs) with
gravity as a known input and the load-cell force u as a known input:

    x' = A x + B2 u + B1 w' + G g                        (w' white road velocity)
    y  = [rattlespace_abs, accel] = C x + D u + y_offset + v,    y_offset = [0, -g]

ZOH discretisation: x[k+1] = Phi x[k] + Gamma_u u[k] + Gamma_g g + w[k] with the
process-noise covariance Qd = int_0^dt e^{As} B1 W B1' e^{A's} ds (Van Loan).  The
steady-state prior covariance P solves the filter DARE; then (measurement-update form)

    F = C P C' + R,    L = P C' F^-1,    x+ = x- + L r,    r = y - C x- - D u - y_offset
    x-[k+1] = Phi x+ + Gamma_u u + Gamma_g g

which fuses into x-[k+1] = filter_A x- + filter_By y + filter_Bu u + filter_b with

    filter_A = Phi (I - L C),  filter_By = Phi L,  filter_Bu = Gamma_u - Phi L D,
    filter_b = Gamma_g g - Phi L y_offset.

Airborne model: with Kt = Ct = 0 the centre-of-mass modes (position and velocity of the
mass-weighted coordinate M x1 + m x2) are two integrators that neither rattlespace nor
acceleration sees, so the filter DARE has no stabilising solution.  The airborne *filter*
model therefore gives those modes a pseudo spring/damper (frequency and damping ratio
from cfg.design.airborne_filter_com_*) acting on the centre of mass only (force split in
proportion to the masses, pre-loaded with the weight so gravity cancels): the relative
dynamics, the measurement equation and hence the residuals are exactly those of the true
airborne model; only the (unobservable) centre-of-mass estimate becomes bounded.

On-ground models: white road velocity has no low-frequency roll-off, and the transfer
from w' to both measurements has a zero at s = 0, so the exact filter has a pole at
~0.999998 (time constant ~10 min) along the common body/wheel velocity and a huge DC gain
from a rattlespace bias to the velocity estimate (~1e8 N of LQ force per metre of bias).
The filter model therefore gets a pseudo leak of rate 2 pi cfg.design.filter_velocity_leak_hz
on the mass-weighted velocity (both accelerations alike, so relative dynamics and the
static equilibrium are unchanged); 0 switches it off (docs/design.md).

Measurement biases (docs/design.md §9.2): :func:`steady_state_kalman` with ``bias_qd``
augments the model with random-walk biases on the rattlespace and/or acceleration
measurement, y = C x + b + D u + y_offset + v; the plant-state gain is ``L`` and the bias
gain ``L_bias``.  The fused runtime form is unchanged with y replaced by y - b-.

Airborne wheel force (§9.4): the airborne filter model also carries a white force on the
wheel of intensity cfg.design.airborne_filter_wheel_force_intensity (the tire force the
model leaves out, ``DiscreteFilterModel.Qd_fixed``), so it tracks the relative motion
instead of predicting it open loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from controller.arrays import FloatArray
from controller.config import RigConfig
from controller.dare import solve_filter_dares
from controller.human_filter import discretize_zoh
from controller.plant import GRAVITY_INPUT, LinearModel

__all__ = [
    "DiscreteFilterModel",
    "FilterModel",
    "FusedFilter",
    "KalmanStack",
    "SteadyStateKalman",
    "bias_augmented",
    "discretize_filter_model",
    "filter_model",
    "fused_prior_update",
    "process_noise_cov",
    "steady_state_kalman",
    "steady_state_kalman_stack",
]


@dataclass(frozen=True)
class FilterModel:
    """Continuous model the filter of model j is built on (regularised if airborne)."""

    A: FloatArray       # (4, 4)
    B2: FloatArray      # (4,)
    B1: FloatArray      # (4,)
    G: FloatArray       # (4,) multiplies g
    C: FloatArray       # (2, 4)
    D: FloatArray       # (2,)
    y_offset: FloatArray  # (2,) = [0, -g]
    gravity_mps2: float
    #: intensity [N^2 s] of a white force on the wheel (airborne model: the tire force it
    #: does not model); 0 for the on-ground models
    wheel_force_intensity: float = 0.0


@dataclass(frozen=True)
class DiscreteFilterModel:
    Phi: FloatArray       # (4, 4)
    Gamma_u: FloatArray   # (4,)
    Gamma_g: FloatArray   # (4,) multiplies g
    Qd_unit: FloatArray   # (4, 4) process-noise covariance for W = 1 m^2/s
    #: (4, 4) road-independent process noise (the airborne model's wheel force)
    Qd_fixed: FloatArray = field(default_factory=lambda: np.zeros((4, 4)))


@dataclass(frozen=True)
class SteadyStateKalman:
    P_prior: FloatArray   # (n, n); with bias states (n + n_b, n + n_b), biases last
    L: FloatArray         # (n, 2) gain of the plant states
    F: FloatArray         # (2, 2)
    F_inv: FloatArray     # (2, 2)
    logdet: float
    #: (2, 2) gain of the measurement-bias states: row 0 rattlespace bias, row 1
    #: acceleration bias (a zero row: that bias state is not modelled)
    L_bias: FloatArray = field(default_factory=lambda: np.zeros((2, 2)))


@dataclass(frozen=True)
class FusedFilter:
    A: FloatArray   # (4, 4)
    By: FloatArray  # (4, 2)
    Bu: FloatArray  # (4,)
    b: FloatArray   # (4,)


def filter_model(model: LinearModel, cfg: RigConfig) -> FilterModel:
    """The filter model of ``model``; airborne gets the centre-of-mass regularisation."""
    g = cfg.vehicle.gravity_mps2
    A = model.A.copy()
    G = GRAVITY_INPUT.copy()
    if model.airborne:
        M, m = cfg.vehicle.sprung_mass_kg, cfg.vehicle.unsprung_mass_kg
        wn = 2.0 * math.pi * cfg.design.airborne_filter_com_hz
        zeta = cfg.design.airborne_filter_com_damping
        # pseudo force per total mass: wn^2 e - 2 zeta wn h',  e = (M x1 + m x2)/(M+m),
        # h' = (M x3 + m x4)/(M+m); it accelerates body and wheel alike (relative
        # dynamics untouched) and carries the weight (so G g cancels).
        mass_w = np.array([M, m]) / (M + m)
        row = np.concatenate([wn**2 * mass_w, -2.0 * zeta * wn * mass_w])
        A[2] += row
        A[3] += row
        G = np.zeros(4)
    elif cfg.design.filter_velocity_leak_hz > 0.0:
        M, m = cfg.vehicle.sprung_mass_kg, cfg.vehicle.unsprung_mass_kg
        lam = 2.0 * math.pi * cfg.design.filter_velocity_leak_hz
        # pseudo leak -lam (M x3 + m x4)/(M+m) on both accelerations: relative dynamics
        # and the static equilibrium are untouched; bounds the common-velocity estimate
        row = -lam * np.array([0.0, 0.0, M, m]) / (M + m)
        A[2] += row
        A[3] += row
    C = model.C_meas.copy()
    w_force = cfg.design.airborne_filter_wheel_force_intensity if model.airborne else 0.0
    return FilterModel(A, model.B2.copy(), model.B1.copy(), G, C, model.D_meas.copy(),
                       np.array([0.0, -g]), g, w_force)


def process_noise_cov(A: FloatArray, B1: FloatArray, W: float, dt_s: float) -> FloatArray:
    """Qd = int_0^dt e^{As} B1 W B1' e^{A's} ds (Van Loan 1978).

    expm([[-A, B1 W B1'], [0, A']] dt) = [[., E12], [0, E22]] with E22 = Phi' and
    Qd = E22' E12.
    """
    n = A.shape[0]
    Bm = B1.reshape(n, -1)
    Wm = np.atleast_2d(W)
    blk = np.zeros((2 * n, 2 * n))
    blk[:n, :n] = -A
    blk[:n, n:] = Bm @ Wm @ Bm.T
    blk[n:, n:] = A.T
    E = scipy.linalg.expm(blk * dt_s)
    Qd = E[n:, n:].T @ E[:n, n:]
    return 0.5 * (Qd + Qd.T)


def discretize_filter_model(fm: FilterModel, dt_s: float) -> DiscreteFilterModel:
    Phi, Gam = discretize_zoh(fm.A, np.column_stack([fm.B2, fm.G]), dt_s)
    fixed = np.zeros((4, 4))
    if fm.wheel_force_intensity > 0.0:      # a force on the wheel alone: -B2 without 1/M
        b_wheel = np.array([0.0, 0.0, 0.0, fm.B2[3]])
        fixed = process_noise_cov(fm.A, b_wheel, fm.wheel_force_intensity, dt_s)
    return DiscreteFilterModel(Phi, Gam[:, 0].copy(), Gam[:, 1].copy(),
                               process_noise_cov(fm.A, fm.B1, 1.0, dt_s), fixed)


def bias_augmented(Phi: FloatArray, C: FloatArray, Qd: FloatArray,
                   bias_qd: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, list[int]]:
    """The filter model with a random-walk bias state on each measurement channel i whose
    per-sample increment variance ``bias_qd[i]`` is > 0:

        [x; b][k+1] = blockdiag(Phi, I) [x; b][k] + noise,   y = [C, E] [x; b] + ...,
        Qd_aug = blockdiag(Qd, diag(bias_qd[kept]))

    (E selects the channel of each kept bias).  Returns (Phi_aug, C_aug, Qd_aug, kept)."""
    n = Phi.shape[0]
    kept = [i for i in range(C.shape[0]) if bias_qd[i] > 0.0]
    nb_ = len(kept)
    Phi_a = np.eye(n + nb_)
    Phi_a[:n, :n] = Phi
    C_a = np.zeros((C.shape[0], n + nb_))
    C_a[:, :n] = C
    Q_a = np.zeros((n + nb_, n + nb_))
    Q_a[:n, :n] = Qd
    for b, i in enumerate(kept):
        C_a[i, n + b] = 1.0
        Q_a[n + b, n + b] = bias_qd[i]
    return Phi_a, C_a, Q_a, kept


#: A filter whose error dynamics have a spectral radius within this of 1 is not stabilising
#: (a marginal mode never forgets its initial error).
_STABLE_MARGIN = 1e-9


def steady_state_kalman(Phi: FloatArray, C: FloatArray, Qd: FloatArray,
                        R: FloatArray, bias_qd: FloatArray | None = None) -> SteadyStateKalman:
    """Steady-state prior covariance (filter DARE) and the measurement-update gain.

    ``bias_qd`` (per measurement channel, per-sample variance of a random-walk bias;
    0 = none) augments the model with measurement-bias states (:func:`bias_augmented`);
    the plant-state gain is then ``L`` and the bias gain ``L_bias``.
    Raises ``ValueError`` if the DARE has no stabilising solution.  The same numbers as
    one system of :func:`steady_state_kalman_stack`, bit for bit.
    """
    t = steady_state_kalman_stack(Phi[None], C[None], Qd[None], R, bias_qd)
    return SteadyStateKalman(t.P_prior[0], t.L[0], t.F[0], t.F_inv[0],
                             float(t.logdet[0]), t.L_bias[0])


@dataclass(frozen=True)
class KalmanStack:
    """:class:`SteadyStateKalman` of N systems, stacked along a leading axis."""

    P_prior: FloatArray   # (N, n, n); with bias states (N, n + n_b, n + n_b)
    L: FloatArray         # (N, n, 2)
    F: FloatArray         # (N, 2, 2)
    F_inv: FloatArray     # (N, 2, 2)
    logdet: FloatArray    # (N,)
    L_bias: FloatArray    # (N, 2, 2)


def steady_state_kalman_stack(Phi: FloatArray, C: FloatArray, Qd: FloatArray,
                              R: FloatArray,
                              bias_qd: FloatArray | None = None) -> KalmanStack:
    """:func:`steady_state_kalman` of N systems at once: ``Phi`` (N, n, n), ``C``
    (N, 2, n), ``Qd`` (N, n, n), one ``R`` (2, 2) and ``bias_qd`` (2,) for all.  The
    DAREs are solved together (:func:`controller.dare.solve_filter_dares`).
    Raises ``ValueError`` naming the first system i (stack index) without a stabilising
    solution."""
    Phi = np.asarray(Phi, dtype=float)
    C = np.asarray(C, dtype=float)
    Qd = np.asarray(Qd, dtype=float)
    N, n, _ = Phi.shape
    kept: list[int] = []
    if bias_qd is not None and np.any(np.asarray(bias_qd) > 0.0):
        aug = [bias_augmented(Phi[i], C[i], Qd[i], np.asarray(bias_qd, dtype=float))
               for i in range(N)]
        kept = aug[0][3]
        Phi = np.stack([a[0] for a in aug])
        C = np.stack([a[1] for a in aug])
        Qd = np.stack([a[2] for a in aug])
    try:
        P = solve_filter_dares(Phi, C, Qd, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ValueError(f"Kalman filter DARE has no stabilising solution ({exc})") from exc
    Ct = np.swapaxes(C, 1, 2)
    F = C @ P @ Ct + R
    F = 0.5 * (F + np.swapaxes(F, 1, 2))
    F_inv = np.linalg.inv(F)
    F_inv = 0.5 * (F_inv + np.swapaxes(F_inv, 1, 2))
    L_all = P @ Ct @ F_inv
    # solve_discrete_are may return a non-stabilising solution without raising (scipy
    # 1.17: the maximal solution for a model with unobservable modes on the unit circle,
    # such as the airborne model's centre of mass): check the error dynamics.
    rho = np.max(np.abs(np.linalg.eigvals(Phi @ (np.eye(Phi.shape[1]) - L_all @ C))),
                 axis=1)
    bad = np.flatnonzero(~(rho < 1.0 - _STABLE_MARGIN))
    if bad.size:
        i = int(bad[0])
        where = f"system {i}: " if N > 1 else ""
        raise ValueError(f"Kalman filter DARE has no stabilising solution "
                         f"({where}error dynamics spectral radius {rho[i]:.12f})")
    sign, logdet = np.linalg.slogdet(F)
    if np.any(sign <= 0):
        raise ValueError("innovation covariance is not positive definite")
    L_bias = np.zeros((N, 2, C.shape[1]))
    for b, i in enumerate(kept):
        L_bias[:, i] = L_all[:, n + b]
    return KalmanStack(P, L_all[:, :n].copy(), F, F_inv.astype(np.float64), logdet, L_bias)


def fused_prior_update(Phi: FloatArray, Gamma_u: FloatArray, Gamma_g: FloatArray,
                       g: float, C: FloatArray, D: FloatArray, y_offset: FloatArray,
                       L: FloatArray) -> FusedFilter:
    """x-[k+1] = A x- + By y + Bu u + b (the update then the propagation, fused)."""
    n = Phi.shape[0]
    A = Phi @ (np.eye(n) - L @ C)
    By = Phi @ L
    Bu = Gamma_u - Phi @ L @ D
    b = Gamma_g * g - Phi @ L @ y_offset
    return FusedFilter(A, By, Bu, b)
