"""Filter Riccati equations solved many at a time (structure-preserving doubling).

The bank's design solves one filter DARE per (model, noise-table entry): thousands of
small systems (5 x 5 with the bias states).  :func:`solve_filter_dares` solves a stack of
them at once with the structure-preserving doubling algorithm (SDA; Chu, Fan, Lin & Wang,
"Structure-preserving algorithms for periodic discrete-time algebraic Riccati
equations", Int. J. Control 77 (2004); the standard doubling recursion of Anderson 1978):
for the filter DARE

    P = Phi P Phi' - Phi P C' (C P C' + R)^-1 C P Phi' + Q

start from A_0 = Phi', G_0 = C' R^-1 C, H_0 = Q and iterate

    W_k = I + G_k H_k
    A_{k+1} = A_k W_k^-1 A_k
    G_{k+1} = G_k + A_k W_k^-1 G_k A_k'
    H_{k+1} = H_k + A_k' H_k W_k^-1 A_k

H_k converges quadratically to the stabilising solution when one exists with the
closed loop strictly inside the unit circle (about 15 iterations for the bank's models,
each a few batched 5 x 5 solves).  One Newton (Hewer) step then polishes it: the doubling
alone leaves residuals up to 1e-9 of |P| on the stiff airborne model, the Newton step
1e-12, as good as the QZ method.  A system stops iterating when its own step is below
``_TOLERANCE`` of its solution, so its result does not depend on which other systems
share the stack (a design and a single-model check agree bit for bit).

A system that has not converged after ``_MAX_ITERATIONS`` (modes on or near the unit
circle converge only linearly, such as the airborne model's centre of mass), whose
doubling step is singular or non-finite, or whose solution leaves a Riccati residual
above ``_RESIDUAL`` is solved by ``scipy.linalg.solve_discrete_are`` instead (the QZ
method), so the answer is never worse than before.  The caller still checks that the
solution is stabilising (:func:`controller.kalman.steady_state_kalman_stack`).

Shapes: ``Phi`` (N, n, n), ``C`` (N, m, n), ``Q`` (N, n, n) and ``R`` (m, m) or
(N, m, m); returns P (N, n, n), symmetric.  Units are those of the model (P has the
units of x x').
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from controller.arrays import FloatArray

__all__ = ["doubling_dares", "solve_filter_dares"]

#: a system has converged when max |H_{k+1} - H_k| <= _TOLERANCE * max |H_{k+1}|
_TOLERANCE = 1e-14
#: ... and max |A_k| <= _DECAYED: the error of H_k is of order A_k' (.) A_k, so a
#: small step alone can be a slow (linear) crawl near the unit circle, not convergence
_DECAYED = 1e-7
#: iterations before a system is handed to the QZ solver (quadratic convergence takes
#: about 15 for the bank's models)
_MAX_ITERATIONS = 40
#: largest accepted Riccati residual after the Newton step, relative to max |P| (the
#: bank's systems reach 1e-12 or less; scipy's QZ 3e-12)
_RESIDUAL = 1e-10


def _transpose(X: FloatArray) -> FloatArray:
    return np.swapaxes(X, -1, -2)


def _sym(X: FloatArray) -> FloatArray:
    return 0.5 * (X + _transpose(X))


def _residual(P: FloatArray, Phi: FloatArray, C: FloatArray, Q: FloatArray,
              R: FloatArray) -> FloatArray:
    """max |residual of the filter DARE| / max |P| per system, shape (N,)."""
    PCt = P @ _transpose(C)
    F = C @ PCt + R
    K = Phi @ PCt
    res = Phi @ P @ _transpose(Phi) - K @ np.linalg.solve(F, _transpose(K)) + Q - P
    scale = np.maximum(np.max(np.abs(P), axis=(1, 2)), np.finfo(float).tiny)
    out: FloatArray = np.max(np.abs(res), axis=(1, 2)) / scale
    return out


def _doubling(Phi: FloatArray, C: FloatArray, Q: FloatArray,
              R: FloatArray) -> tuple[FloatArray, np.ndarray]:
    """SDA on every system; returns (P, converged mask)."""
    N, n, _ = Phi.shape
    A = _transpose(Phi).copy()
    G = _sym(_transpose(C) @ np.linalg.solve(R, C))
    H = _sym(Q).copy()
    converged = np.zeros(N, dtype=bool)
    active = np.arange(N)
    eye = np.eye(n)
    with np.errstate(all="ignore"):
        for _ in range(_MAX_ITERATIONS):
            if active.size == 0:
                break
            a, g, h = A[active], G[active], H[active]
            try:
                X = np.linalg.solve(eye + g @ h, np.concatenate([a, g], axis=2))
            except np.linalg.LinAlgError:
                break           # a singular step: the QZ solver takes the rest
            Wa, Wg = X[:, :, :n], X[:, :, n:]
            a_t = _transpose(a)
            h_next = _sym(h + a_t @ h @ Wa)
            A[active] = a @ Wa
            G[active] = _sym(g + a @ Wg @ a_t)
            step = np.max(np.abs(h_next - h), axis=(1, 2))
            size = np.max(np.abs(h_next), axis=(1, 2))
            H[active] = h_next
            finite = np.isfinite(step) & np.isfinite(size)
            a_size = np.max(np.abs(A[active]), axis=(1, 2))
            done = finite & (step <= _TOLERANCE * size) & (a_size <= _DECAYED)
            converged[active[done]] = True
            active = active[finite & ~done]
    return H, converged


def _stein(Ac: FloatArray, rhs: FloatArray) -> FloatArray:
    """X = Ac X Ac' + rhs for each system of a stack (Smith's doubling: X = sum of
    Ac^k rhs Ac'^k, summed in 2^j blocks by squaring Ac), every system to its own
    convergence (so a result does not depend on the stack); NaN where Ac is not
    contracting within ``_MAX_ITERATIONS`` squarings."""
    X = rhs.copy()
    A = Ac.copy()
    active = np.arange(X.shape[0])
    for _ in range(_MAX_ITERATIONS):
        if active.size == 0:
            break
        a, x = A[active], X[active]
        step = a @ x @ _transpose(a)
        x_next = x + step
        X[active] = x_next
        A[active] = a @ a
        small = np.max(np.abs(step), axis=(1, 2)) <= _TOLERANCE * np.max(np.abs(x_next),
                                                                           axis=(1, 2))
        decayed = np.max(np.abs(A[active]), axis=(1, 2)) <= _DECAYED
        finite = np.all(np.isfinite(x_next), axis=(1, 2))
        active = active[finite & ~(small & decayed)]
    X[active] = np.nan
    return _sym(X)


def _newton_step(P: FloatArray, Phi: FloatArray, C: FloatArray, Q: FloatArray,
                 R: FloatArray) -> FloatArray:
    """One Newton (Hewer) step from P: with the filter gain K of P and the closed loop
    A_c = Phi - K C, the P' solving the Stein equation P' = A_c P' A_c' + Q + K R K'."""
    Ct = _transpose(C)
    K = Phi @ P @ Ct @ np.linalg.inv(C @ P @ Ct + R)
    Ac = Phi - K @ C
    return _stein(Ac, Q + K @ R @ _transpose(K))


def _as_stack(Phi: FloatArray, C: FloatArray, Q: FloatArray, R: FloatArray
              ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The arguments as float stacks, R broadcast to one (m, m) per system."""
    Phi = np.asarray(Phi, dtype=float)
    R = np.asarray(R, dtype=float)
    return (Phi, np.asarray(C, dtype=float), np.asarray(Q, dtype=float),
            np.broadcast_to(R, (Phi.shape[0], *R.shape[-2:])))


def doubling_dares(Phi: FloatArray, C: FloatArray, Q: FloatArray,
                   R: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The doubling and Newton steps of :func:`solve_filter_dares` without the QZ
    fallback: (P, solved) with ``solved[i]`` False where system i did not converge or
    left a residual above ``_RESIDUAL`` (its P is then not a solution).  For a caller
    with its own fallback (:func:`controller.lq.dlqr_cross_stack`)."""
    Phi, C, Q, R = _as_stack(Phi, C, Q, R)
    P, ok = _doubling(Phi, C, Q, R)
    if np.any(ok):
        idx = np.flatnonzero(ok)
        with np.errstate(all="ignore"):
            try:
                P[idx] = _newton_step(P[idx], Phi[idx], C[idx], Q[idx], R[idx])
                res = _residual(P[idx], Phi[idx], C[idx], Q[idx], R[idx])
            except np.linalg.LinAlgError:
                res = np.full(idx.size, np.inf)
        ok[idx[~(res <= _RESIDUAL)]] = False
    return P, ok


def solve_filter_dares(Phi: FloatArray, C: FloatArray, Q: FloatArray,
                       R: FloatArray) -> FloatArray:
    """Stabilising solutions P of the filter DAREs of a stack of systems (module doc).

    Raises ``ValueError`` (naming the stack index i of a stack) for a system that
    neither method solves."""
    Phi, C, Q, R = _as_stack(Phi, C, Q, R)
    N = Phi.shape[0]
    P, ok = doubling_dares(Phi, C, Q, R)
    for i in np.flatnonzero(~ok):
        try:
            P[i] = _sym(scipy.linalg.solve_discrete_are(Phi[i].T, C[i].T, Q[i], R[i]))
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise ValueError(f"system {i}: {exc}" if N > 1 else str(exc)) from exc
    return P
