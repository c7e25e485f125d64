"""LQ gains of the bank on the discrete controller rate (thesis Ch. II, Eq. 2.5, 2.9).

Augmented plant per model j (deviations from the model's static equilibrium, where
gravity cancels): z = [x (4 plant states); xf (2 human-filter states)],

    x'  = A x + B2 u + B1 w'
    xf' = Af xf + Bf a,       a = A[2] x + u / M    (sprung acceleration, feedthrough of u)

Cost (Eq. 2.5, built here; the printed Eq. 2.6-2.8 are garbled):

    J = int rho4 y_f^2 + rho1 x2^2 + rho2 (x1 - x2)^2 + rho3 u^2 dt,     y_f = Cf xf

i.e. z' Qc z + rho3 u^2 with no continuous cross term (y_f is strictly proper).  The
controller runs at dt with a zero-order-hold force, so the cost is integrated exactly
over one sample (Van Loan, :func:`discretize_cost`), which yields discrete Qd, Rd and a
cross term Nd, and the gain solves the DARE with that cross term:

    u_k = -K z_k,    K = (Rd + Bd' P Bd)^-1 (Bd' P Ad + Nd').

The airborne model (Kt = Ct = 0) gets K = 0: in the thesis's Ch. VI the airborne
controller's output is zero, and its centre-of-mass modes (two integrators) are
uncontrollable by an internal force, so its DARE has no stabilising solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from controller.actuator import ServoModel
from controller.arrays import FloatArray
from controller.dare import doubling_dares
from controller.human_filter import HumanFilter, discretize_zoh
from controller.plant import LinearModel

__all__ = [
    "ACTUATOR_GAIN_OFFSET",
    "AugmentedPlant",
    "DiscreteLQProblem",
    "LQStackError",
    "actuated_lq_gain",
    "actuated_lq_problem",
    "actuated_plant",
    "augmented_plant",
    "discretize_cost",
    "dlqr_cross",
    "dlqr_cross_stack",
    "lq_gain",
    "lq_problem",
]


@dataclass(frozen=True)
class AugmentedPlant:
    """Continuous augmented plant z' = A z + B u + B1 w' and cost z'Qc z + Rc u^2.

    z = [x (4), xf (2)]: the quarter-car state (SI) followed by the human-body filter's
    states; u is the actuator force [N], w' the road velocity [m/s]."""

    A: FloatArray   # (6, 6)
    B: FloatArray   # (6,)
    B1: FloatArray  # (6,)
    Qc: FloatArray  # (6, 6)
    Rc: float
    Cf: FloatArray  # (2,) y_f = Cf xf
    inv_mass: float  # 1 / M, the feedthrough of u into the acceleration


@dataclass(frozen=True)
class DiscreteLQProblem:
    """Sampled LQ problem: z+ = Ad z + Bd u, stage cost z'Qd z + 2 z'Nd u + Rd u^2."""

    Ad: FloatArray
    Bd: FloatArray
    Qd: FloatArray
    Rd: float
    Nd: FloatArray
    dt_s: float


def augmented_plant(model: LinearModel, hf: HumanFilter,
                    weights: tuple[float, float, float, float] | list[float]) -> AugmentedPlant:
    """Augment model j with F(s) and build the Eq. 2.5 cost for [rho1, rho2, rho3, rho4]."""
    rho1, rho2, rho3, rho4 = (float(w) for w in weights)
    if rho3 <= 0.0 or min(rho1, rho2, rho4) < 0.0:
        raise ValueError(f"weights {list(weights)}: need rho3 > 0 and rho1, rho2, rho4 >= 0")
    inv_m = float(model.B2[2])  # 1/M
    A = np.zeros((6, 6))
    A[:4, :4] = model.A
    A[4:, :4] = np.outer(hf.Bf, model.A[2])
    A[4:, 4:] = hf.Af
    B = np.concatenate([model.B2, hf.Bf * inv_m])
    B1 = np.concatenate([model.B1, hf.Bf * model.B1[2]])
    e_rattle = np.array([1.0, -1.0, 0.0, 0.0, 0.0, 0.0])
    e_tire = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    c_f = np.concatenate([np.zeros(4), hf.Cf])
    Qc = rho1 * np.outer(e_tire, e_tire) + rho2 * np.outer(e_rattle, e_rattle) \
        + rho4 * np.outer(c_f, c_f)
    return AugmentedPlant(A, B, B1, Qc, rho3, hf.Cf.copy(), inv_m)


def discretize_cost(A: FloatArray, B: FloatArray, Qc: FloatArray, Rc: float,
                    dt_s: float, Nc: FloatArray | None = None) -> DiscreteLQProblem:
    """Exact sampled-data LQ problem for a ZOH input (Van Loan 1978).

    With xi = [z; u], xi' = Ahat xi (u held), the cost over one sample is
    xi_k' (int_0^dt e^{Ahat' t} Qhat e^{Ahat t} dt) xi_k, Qhat = [[Qc, Nc], [Nc', Rc]].
    Van Loan: expm([[-Ahat', Qhat], [0, Ahat]] dt) = [[., E12], [0, E22]] and the
    integral is E22' E12.
    """
    n = A.shape[0]
    Bm = B.reshape(n, 1)
    Ahat = np.zeros((n + 1, n + 1))
    Ahat[:n, :n] = A
    Ahat[:n, n:] = Bm
    Qhat = np.zeros((n + 1, n + 1))
    Qhat[:n, :n] = Qc
    Qhat[n, n] = Rc
    if Nc is not None:
        Qhat[:n, n] = Nc
        Qhat[n, :n] = Nc
    k = n + 1
    blk = np.zeros((2 * k, 2 * k))
    blk[:k, :k] = -Ahat.T
    blk[:k, k:] = Qhat
    blk[k:, k:] = Ahat
    E = scipy.linalg.expm(blk * dt_s)
    Qint = E[k:, k:].T @ E[:k, k:]
    Qint = 0.5 * (Qint + Qint.T)
    Ad, Bd = discretize_zoh(A, B, dt_s)
    return DiscreteLQProblem(Ad, Bd, Qint[:n, :n], float(Qint[n, n]), Qint[:n, n].copy(),
                             float(dt_s))


class LQStackError(ValueError):
    """A problem of :func:`dlqr_cross_stack` has no stabilising solution: ``index`` is
    its place in the stack, ``reason`` what failed (the message names the index only
    for a stack of more than one)."""

    def __init__(self, index: int, size: int, reason: str) -> None:
        super().__init__(f"system {index}: {reason}" if size > 1 else reason)
        self.index = index
        self.reason = reason


def dlqr_cross_stack(Ad: FloatArray, Bd: FloatArray, Qd: FloatArray, Rd: FloatArray,
                     Nd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Discrete LQR with cross term for a stack of single-input problems: (K (S, n),
    P (S, n, n)) with u = -K[i] z for problem i.  Shapes: ``Ad`` (S, n, n), ``Bd``, ``Nd``
    (S, n), ``Qd`` (S, n, n), ``Rd`` (S,).

    Each problem's input is rescaled to unit cost weight (rho3 = 1e-8 makes Rd tiny next
    to Qd in SI units) and its state by the diagonal similarity z = T z~ that balances
    Ad (``scipy.linalg.matrix_balance``, powers of two: exact; SI states span metres to
    newtons, and with the actuator's pending commands the pencil is otherwise too
    ill-conditioned); gain and P are transformed back.  The cross term is taken into
    the standard form (A - B N', Q - N N' with the unit input weight), and the stack is
    solved together by doubling (:func:`controller.dare.doubling_dares`, the filter
    DARE of the dual system).  A problem the doubling does not solve goes to scipy's
    QZ solver with the cross term, and, if scipy's own pencil balancing leaves the QZ
    reordering ill-conditioned (some actuated problems with D >= 2), again without it.
    Each problem's result does not depend on the others in the stack.  Raises
    ``ValueError`` (naming the stack index i of a stack) if a DARE has no stabilising
    solution.
    """
    Ad = np.asarray(Ad, dtype=float)
    S, n, _ = Ad.shape
    Bd = np.asarray(Bd, dtype=float).reshape(S, n)
    Nd = np.asarray(Nd, dtype=float).reshape(S, n)
    Qd = np.asarray(Qd, dtype=float)
    Rd = np.asarray(Rd, dtype=float).reshape(S)
    t = np.empty((S, n))
    for i in range(S):
        _, (t[i], _) = scipy.linalg.matrix_balance(Ad[i], permute=False, separate=True)
    t_inv = 1.0 / t
    scale = 1.0 / np.sqrt(Rd)  # u = scale * v  ->  cost weight on v is 1
    Ab = Ad * t_inv[:, :, None] * t[:, None, :]
    Qb = Qd * t[:, :, None] * t[:, None, :]
    Bv = Bd * t_inv * scale[:, None]
    Nv = Nd * t * scale[:, None]
    one = np.ones((1, 1))
    # standard form: A~ = Ab - Bv Nv', Q~ = Qb - Nv Nv'; its filter DARE dual is
    # Phi = A~', C = Bv'
    A_std = Ab - Bv[:, :, None] * Nv[:, None, :]
    Q_std = Qb - Nv[:, :, None] * Nv[:, None, :]
    Q_std = 0.5 * (Q_std + np.swapaxes(Q_std, 1, 2))
    Pb, ok = doubling_dares(np.swapaxes(A_std, 1, 2), Bv[:, None, :], Q_std, one)
    for k in np.flatnonzero(~ok):
        b, nv = Bv[k].reshape(n, 1), Nv[k].reshape(n, 1)
        try:
            Pb[k] = scipy.linalg.solve_discrete_are(Ab[k], b, Qb[k], one, s=nv)
        except (np.linalg.LinAlgError, ValueError):
            try:
                Pb[k] = scipy.linalg.solve_discrete_are(Ab[k], b, Qb[k], one, s=nv,
                                                        balanced=False)
            except (np.linalg.LinAlgError, ValueError) as exc:
                raise LQStackError(int(k), S, "LQ DARE has no stabilising solution "
                                   f"({exc})") from exc
    PB = Pb @ Bv[:, :, None]                                        # (S, n, 1)
    denom = 1.0 + (Bv[:, None, :] @ PB)[:, 0, 0]
    Kv = ((np.swapaxes(PB, 1, 2) @ Ab)[:, 0, :] + Nv) / denom[:, None]
    K = Kv * scale[:, None] * t_inv
    P = Pb * t_inv[:, :, None] * t_inv[:, None, :]
    rho = np.max(np.abs(np.linalg.eigvals(Ad - Bd[:, :, None] * K[:, None, :])), axis=1)
    unstable = np.flatnonzero(~(rho < 1.0))
    if unstable.size:
        first = int(unstable[0])
        raise LQStackError(first, S, "LQ closed loop not stable (spectral radius "
                                     f"{rho[first]:.6f})")
    return K, P


def dlqr_cross(Ad: FloatArray, Bd: FloatArray, Qd: FloatArray, Rd: float,
               Nd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Discrete LQR with cross term: (K (n,), P (n, n)) for u = -K z; the one-problem
    case of :func:`dlqr_cross_stack` (the same numbers as in a stack).  Raises
    ``ValueError`` if the DARE has no stabilising solution."""
    n = Ad.shape[0]
    K, P = dlqr_cross_stack(Ad.reshape(1, n, n), np.reshape(Bd, (1, n)), Qd.reshape(1, n, n),
                            np.array([Rd], dtype=float), np.reshape(Nd, (1, n)))
    return K[0], P[0]


def lq_problem(model: LinearModel, hf: HumanFilter,
               weights: tuple[float, float, float, float] | list[float]) -> DiscreteLQProblem:
    aug = augmented_plant(model, hf, weights)
    return discretize_cost(aug.A, aug.B, aug.Qc, aug.Rc, hf.dt_s)


def lq_gain(model: LinearModel, hf: HumanFilter,
            weights: tuple[float, float, float, float] | list[float]) -> FloatArray:
    """The (6,) gain of model j for one weight set; zeros for the airborne model."""
    if model.airborne:
        return np.zeros(6)
    prob = lq_problem(model, hf, weights)
    K, _ = dlqr_cross(prob.Ad, prob.Bd, prob.Qd, prob.Rd, prob.Nd)
    return K


#: Gain layout of the actuator-aware design: [Kx (4), Kf (2), K_spool, K_force, K_rate,
#: K_pending (D)]; the first 6 entries have the meaning of :func:`lq_gain`'s, K_rate acts
#: on the state w of the flow feedforward's rate filter (:mod:`controller.actuator`).
ACTUATOR_GAIN_OFFSET = 6


def actuated_plant(model: LinearModel, hf: HumanFilter, servo: ServoModel
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Continuous plant + human filter + linearised actuator, states
    [x (4), xf (2), x_v, F], spool command input: (A (8, 8), B_spool (8,), B1 (8,))."""
    inv_m = float(model.B2[2])
    n = 8
    A8 = np.zeros((n, n))
    A8[:4, :4] = model.A
    A8[:4, 7] = model.B2
    A8[4:6, :4] = np.outer(hf.Bf, model.A[2])
    A8[4:6, 4:6] = hf.Af
    A8[4:6, 7] = hf.Bf * inv_m
    a_act, b_s = servo.continuous()
    A8[6:8, [0, 1, 2, 3, 6, 7]] = a_act
    B8 = np.zeros(n)
    B8[6:8] = b_s
    B1 = np.zeros(n)
    B1[:4] = model.B1
    B1[4:6] = hf.Bf * model.B1[2]
    return A8, B8, B1


def actuated_lq_problem(model: LinearModel, hf: HumanFilter,
                        weights: tuple[float, float, float, float] | list[float],
                        servo: ServoModel) -> DiscreteLQProblem:
    """Sampled LQ problem with the force path of :mod:`controller.actuator` (docs/design.md
    section 7).  State Z = [x (4), xf (2), x_v, F, w, s_{k-1}, ..., s_{k-D}], input = the
    force reference fref_k.  The force loop's proportional path and flow feedforward make
    the spool command s_k = kp (fref_k - F_k) - c (w_k + b r_k) (linearised at zero load
    pressure; r_k = x1 - x2 the rattlespace, w the state of the rate filter,
    w_{k+1} = (1 - a) w_k - a b r_k), the valve gets s_{k-D} (ZOH over the tick).

    The cost is Eq. 2.5 integrated exactly over the tick along the actuated motion (Van
    Loan with the applied spool as the held input) plus rho3 fref_k^2 T: the thesis's
    u is the commanded force, with an ideal actuator this is :func:`lq_problem`'s cost.
    """
    rho1, rho2, rho3, rho4 = (float(w) for w in weights)
    if rho3 <= 0.0 or min(rho1, rho2, rho4) < 0.0:
        raise ValueError(f"weights {list(weights)}: need rho3 > 0 and rho1, rho2, rho4 >= 0")
    dt = hf.dt_s
    n = 8
    A8, B8, _ = actuated_plant(model, hf, servo)
    e_rattle = np.zeros(n)
    e_rattle[:2] = [1.0, -1.0]
    e_tire = np.zeros(n)
    e_tire[1] = 1.0
    c_f = np.zeros(n)
    c_f[4:6] = hf.Cf
    Qc = rho1 * np.outer(e_tire, e_tire) + rho2 * np.outer(e_rattle, e_rattle) \
        + rho4 * np.outer(c_f, c_f)
    base = discretize_cost(A8, B8, Qc, 0.0, dt)
    ff = servo.feedforward
    a_ff, b_ff, c_ff = ff.rate_filter_coeff, ff.rate_input_gain_per_s, ff.gain_s_per_m
    D = int(servo.delay_ticks)
    iw = n                                   # index of w in Z
    n0 = n + 1                               # first pending command
    N = n0 + D
    e_r = np.zeros(N)
    e_r[:2] = [1.0, -1.0]
    s_z = np.zeros(N)                        # s_k = s_z Z + s_f fref
    s_z[7] = -servo.kp_per_n
    s_z[iw] = -c_ff
    s_z -= c_ff * b_ff * e_r
    s_f = servo.kp_per_n
    if D == 0:
        a_z, a_f = s_z, s_f
    else:
        a_z = np.zeros(N)
        a_z[n0 + D - 1] = 1.0
        a_f = 0.0
    Ad = np.zeros((N, N))
    Bd = np.zeros(N)
    Ad[:n, :n] = base.Ad
    Ad[:n] += np.outer(base.Bd, a_z)
    Bd[:n] = base.Bd * a_f
    Ad[iw] = -a_ff * b_ff * e_r
    Ad[iw, iw] = 1.0 - a_ff
    if D:
        Ad[n0] = s_z
        Bd[n0] = s_f
        for i in range(1, D):
            Ad[n0 + i, n0 + i - 1] = 1.0
    Qbig = np.zeros((n + 1, n + 1))
    Qbig[:n, :n] = base.Qd
    Qbig[:n, n] = base.Nd
    Qbig[n, :n] = base.Nd
    Qbig[n, n] = base.Rd
    T = np.zeros((n + 1, N + 1))
    T[:n, :n] = np.eye(n)
    T[n, :N] = a_z
    T[n, N] = a_f
    C = T.T @ Qbig @ T
    C[N, N] += rho3 * dt
    C = 0.5 * (C + C.T)
    return DiscreteLQProblem(Ad, Bd, C[:N, :N], float(C[N, N]), C[:N, N].copy(), float(dt))


def actuated_lq_gain(model: LinearModel, hf: HumanFilter,
                     weights: tuple[float, float, float, float] | list[float],
                     servo: ServoModel) -> FloatArray:
    """The (9 + D,) gain fref = -K Z of :func:`actuated_lq_problem`; zeros if airborne."""
    D = int(servo.delay_ticks)
    if model.airborne:
        return np.zeros(9 + D)
    prob = actuated_lq_problem(model, hf, weights, servo)
    K, _ = dlqr_cross(prob.Ad, prob.Bd, prob.Qd, prob.Rd, prob.Nd)
    return K
