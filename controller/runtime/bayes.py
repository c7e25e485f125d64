"""Bayesian multiple-model blending (Magill MMAE; thesis Eq. 4.2 and 4.6).

For the contributing models j, with likelihood quotient q_j = r_j' F_j^-1 r_j:

    f_j = exp(-q_j / 2) / ((2π)^{m/2} |F_j|^{1/2})          (4.6, m = measurement dim)
    p_j = f_j p_j(prev) / Σ_k f_k p_k(prev)                    (4.2)

computed in log space (log-sum-exp) so that no exp underflows to 0/0.  Afterwards every
probability is raised to at least ``floor`` and the set renormalised, so that no model
is locked out for ever (a model at p = 0 could never come back).  If no likelihood is
usable (all log-likelihoods -inf or NaN) the probabilities fall back to uniform.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["bayes_update", "log_likelihood_constant"]


def log_likelihood_constant(logdet_f: float, meas_dim: int) -> float:
    """log of 1 / ((2π)^{m/2} |F|^{1/2})."""
    return -0.5 * meas_dim * math.log(2.0 * math.pi) - 0.5 * logdet_f


@nb.njit(cache=True, nogil=True)
def bayes_update(st: np.ndarray, col_p: int, col_q: int, col_contrib: int, vec: np.ndarray,
                 col_llc: int, floor: float, rows: np.ndarray, row0: int, n_rows: int) -> None:
    """In-place MMAE update of st[:, col_p] over the rows j = rows[row0 : row0 + n_rows]
    (the running filters); those with st[j, col_contrib] != 0 are updated, the others
    get p = 0.  ``vec[:, col_llc]`` holds log_likelihood_constant.  Rows not listed are
    left alone.  Allocation-free.
    """
    lmax = -np.inf
    n = 0
    for a in range(n_rows):
        j = rows[row0 + a]
        if st[j, col_contrib] == 0.0:
            st[j, col_p] = 0.0
        else:
            n += 1
            pj = st[j, col_p]
            lp = math.log(pj) if pj > 0.0 else -745.0
            lj = lp + vec[j, col_llc] - 0.5 * st[j, col_q]
            st[j, col_p] = lj          # hold the log value for now
            if lj > lmax:
                lmax = lj
    if n == 0:
        return
    if not (lmax > -np.inf):           # no usable likelihood: uniform
        for a in range(n_rows):
            j = rows[row0 + a]
            if st[j, col_contrib] != 0.0:
                st[j, col_p] = 1.0 / n
        return
    total = 0.0
    for a in range(n_rows):
        j = rows[row0 + a]
        if st[j, col_contrib] != 0.0:
            e = math.exp(st[j, col_p] - lmax)
            st[j, col_p] = e
            total += e
    total2 = 0.0
    for a in range(n_rows):
        j = rows[row0 + a]
        if st[j, col_contrib] != 0.0:
            pj = st[j, col_p] / total
            if pj < floor:
                pj = floor
            st[j, col_p] = pj
            total2 += pj
    for a in range(n_rows):
        j = rows[row0 + a]
        if st[j, col_contrib] != 0.0:
            st[j, col_p] = st[j, col_p] / total2
