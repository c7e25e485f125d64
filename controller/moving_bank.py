"""Moving bank supervisor (thesis Ch. VI; Maybeck & Schore's moving-bank MMAE).

The models form a grid (deflection index x tire-damping-scale index, ``grid_index``)
plus the airborne model.  Two sets:

* **on-ground set** -- a moving subset of k = ``moving_bank.active_models`` grid models,
  the k nearest (in grid steps; ties prefer the deflection axis) to the *centre*;
* **airborne set** -- the airborne model, plus one *sentinel*: the last on-ground centre
  keeps running with zero weight ("even if the filter starts running ... the final
  output ... is still zero", Ch. VI) so that the return to the ground can be detected.

Switched-off filters do no work and contribute zero.  The switching signal is
s = smoothed min q of the running on-ground filters (EWMA, ``smoothing_time_s``).
The threshold T is *learnt from history*: the ``threshold_quantile`` quantile of s over an
exponential window of ``history_window_s`` (a log-spaced histogram with exponential
forgetting), learnt only while on the ground and settled, and never below the chi-square
quantile -2 ln(1 - quantile) that a matched filter's q (m = 2) exceeds with probability
1 - quantile.  Until enough history is learnt T is that floor.

    on ground --(s > T, dwell elapsed)--> airborne
    airborne  --(s_sentinel < hysteresis_ratio * T, dwell elapsed)--> on ground

Within the on-ground set the subset is re-centred on the best model (min smoothed q) when
qs[best] < RECENTRE_RATIO * qs[centre] and ``dwell_time_s`` has elapsed since the last
re-centre.  So that every grid direction gets explored even with small k (a 9 x 3 grid
and k = 3 would otherwise only ever move along the deflection axis), every probe period
the worst non-centre member is swapped for the next candidate in the centre's
neighbour list (round robin over the next ``nprobe`` nearest).  A newly activated
filter starts bumpless -- at its own equilibrium plus the blended deviation from
equilibrium (:func:`controller.kernels.activate`) -- with the centre's smoothed q; at
touch-down the blend is the airborne filter's, so the returning on-ground filters start
from the sentinel's deviation instead (the on-ground view that just passed the test).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from controller.kernels import (
    F_FORGET,
    F_HINC,
    F_HLO,
    F_HTOT,
    F_HWIDTH,
    F_HYST,
    F_QUANT,
    F_RECENTRE,
    F_SIGNAL,
    F_TFLOOR,
    F_THRESH,
    F_XDEV,
    F_XDEVM,
    I_AIR,
    I_CENTRE,
    I_DWELL,
    I_HIST,
    I_K,
    I_MINLEARN,
    I_MODE,
    I_NACT,
    I_NB,
    I_NG,
    I_NLEARN,
    I_NPROBE,
    I_NRECENTRE,
    I_NSWITCH,
    I_PROBE,
    I_PROBE_CNT,
    I_PROBE_PTR,
    I_RECOMP,
    I_SENTINEL,
    I_SINCE_RECENTRE,
    I_SINCE_SWITCH,
    IV_ACT,
    M_XBAR,
    MODE_AIR,
    MODE_GROUND,
    S_P,
    S_QS,
    S_W,
    S_XPOST,
    S_XPRIOR,
    V_AIR,
    activate,
    deactivate,
)

__all__ = [
    "HIST_BINS",
    "HIST_HI_LOG10",
    "HIST_LO_LOG10",
    "RECENTRE_RATIO",
    "chi2_threshold_floor",
    "enter_moving",
    "history_add",
    "history_quantile",
    "neighbour_table",
    "supervise",
]

RECENTRE_RATIO = 0.9        # a neighbour must be 10 % better than the centre to take over
HIST_BINS = 128
HIST_LO_LOG10 = -3.0
HIST_HI_LOG10 = 7.0
HIST_RECOMPUTE_TICKS = 16   # the quantile is re-read from the histogram this often
MAX_PROBE_CANDIDATES = 8



def chi2_threshold_floor(quantile: float, meas_dim: int = 2) -> float:
    """The q a matched filter exceeds with probability 1 - quantile (chi-square, m = 2 dof;
    for other m this is the exponential-tail approximation m/2 * -2 ln(1 - quantile))."""
    return -float(meas_dim) * math.log(1.0 - quantile)


def neighbour_table(grid_index: NDArray[np.int64], airborne: NDArray[np.bool_]
                    ) -> NDArray[np.int64]:
    """(J, n_ground): for each on-ground model c, the on-ground models ordered by grid
    distance from c (Euclidean in index steps; ties: smaller damping-index offset first,
    then model index).  Row c starts with c itself.  Airborne rows are -1."""
    J = int(grid_index.shape[0])
    ground = [j for j in range(J) if not airborne[j]]
    out = -np.ones((J, len(ground)), dtype=np.int64)
    for c in ground:
        dc, sc = int(grid_index[c, 0]), int(grid_index[c, 1])

        def key(j: int, dc: int = dc, sc: int = sc) -> tuple[int, int, int]:
            dd = int(grid_index[j, 0]) - dc
            ds = int(grid_index[j, 1]) - sc
            return (dd * dd + ds * ds, abs(ds), j)

        out[c, :] = sorted(ground, key=key)
    return out


# ---------------------------------------------------------------------------- history


@nb.njit(cache=True, nogil=True)
def history_add(fv: np.ndarray, iv: np.ndarray, s: float) -> None:
    """Add one sample of the switching signal to the exponentially forgotten histogram."""
    off = iv[I_HIST]
    nb_ = iv[I_NB]
    inc = fv[F_HINC] * fv[F_FORGET]
    if inc > 1e100:                    # rescale everything (rare): keeps the numbers finite
        scale = 1.0 / inc
        for b in range(nb_):
            fv[off + b] *= scale
        fv[F_HTOT] *= scale
        inc = 1.0
    fv[F_HINC] = inc
    b = int((math.log10(s) - fv[F_HLO]) / fv[F_HWIDTH]) if s > 0.0 else 0
    b = min(max(b, 0), nb_ - 1)
    fv[off + b] += inc
    fv[F_HTOT] += inc
    iv[I_NLEARN] += 1


@nb.njit(cache=True, nogil=True)
def history_quantile(fv: np.ndarray, iv: np.ndarray, quantile: float) -> float:
    """The ``quantile`` of the learnt history (log-linear inside the bin)."""
    off = iv[I_HIST]
    nb_ = iv[I_NB]
    target = quantile * fv[F_HTOT]
    cum = 0.0
    for b in range(nb_):
        c = fv[off + b]
        if c > 0.0 and cum + c >= target:
            frac = (target - cum) / c
            return 10.0 ** (fv[F_HLO] + (b + frac) * fv[F_HWIDTH])
        cum += c
    return 10.0 ** (fv[F_HLO] + nb_ * fv[F_HWIDTH])


# ---------------------------------------------------------------------------- subset moves


@nb.njit(cache=True, nogil=True)
def _move_to(centre: int, st: np.ndarray, active: np.ndarray, fv: np.ndarray,
             iv: np.ndarray, nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray) -> None:
    """Active set := the k nearest grid models of ``centre`` (no airborne model)."""
    k = iv[I_K]
    ng = iv[I_NG]
    J = st.shape[0]
    qs0 = st[centre, S_QS]
    p0 = 1.0 / k
    for j in range(J):                     # switch off what is not in the new subset
        if active[j]:
            keep = False
            if vec[j, V_AIR] == 0.0:
                for i in range(min(k, ng)):
                    if nbr[centre, i] == j:
                        keep = True
            if not keep:
                deactivate(j, st, active, iv)
    for i in range(min(k, ng)):
        j = nbr[centre, i]
        if not active[j]:
            activate(j, st, active, fv, iv, mat, qs0, p0)
    iv[I_CENTRE] = centre
    iv[I_SINCE_RECENTRE] = 0
    iv[I_PROBE_PTR] = 0
    iv[I_PROBE_CNT] = 0


@nb.njit(cache=True, nogil=True)
def enter_moving(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
                 nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray, centre: int) -> None:
    """Start the moving bank on the ground, centred on ``centre``."""
    iv[I_MODE] = MODE_GROUND
    iv[I_SENTINEL] = -1
    iv[I_SINCE_SWITCH] = 0
    _move_to(centre, st, active, fv, iv, nbr, vec, mat)


@nb.njit(cache=True, nogil=True)
def supervise(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
              nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray) -> None:
    """After a tick: learn the threshold, switch sets, re-centre or probe (for next tick)."""
    J = st.shape[0]
    dwell = iv[I_DWELL]
    iv[I_SINCE_SWITCH] += 1
    iv[I_SINCE_RECENTRE] += 1
    air = iv[I_AIR]
    if iv[I_MODE] == MODE_GROUND:
        best = -1
        s = np.inf
        for a in range(iv[I_NACT]):
            j = iv[IV_ACT + a]
            if vec[j, V_AIR] == 0.0 and st[j, S_QS] < s:
                s = st[j, S_QS]
                best = j
        fv[F_SIGNAL] = s
        settled = iv[I_SINCE_SWITCH] >= dwell
        if settled:
            history_add(fv, iv, s)
            if iv[I_NLEARN] >= iv[I_MINLEARN] and iv[I_NLEARN] % iv[I_RECOMP] == 0:
                fv[F_THRESH] = max(history_quantile(fv, iv, fv[F_QUANT]), fv[F_TFLOOR])
        centre = iv[I_CENTRE]
        if air >= 0 and settled and s > fv[F_THRESH]:
            # lift-off: the airborne set takes over; the centre stays as zero-weight sentinel
            for j in range(J):
                if active[j] and j != centre:
                    deactivate(j, st, active, iv)
            activate(air, st, active, fv, iv, mat, st[centre, S_QS], 1.0)
            st[centre, S_P] = 0.0
            st[centre, S_W] = 0.0
            iv[I_SENTINEL] = centre
            iv[I_MODE] = MODE_AIR
            iv[I_SINCE_SWITCH] = 0
            iv[I_NSWITCH] += 1
            return
        if best >= 0 and best != centre and iv[I_SINCE_RECENTRE] >= dwell \
                and st[best, S_QS] < fv[F_RECENTRE] * st[centre, S_QS]:
            _move_to(best, st, active, fv, iv, nbr, vec, mat)
            iv[I_NRECENTRE] += 1
            return
        nprobe = iv[I_NPROBE]
        if nprobe > 0 and iv[I_K] >= 2:
            iv[I_PROBE_CNT] += 1
            if iv[I_PROBE_CNT] >= iv[I_PROBE]:
                iv[I_PROBE_CNT] = 0
                k = iv[I_K]
                for _ in range(nprobe):           # next candidate that is not running
                    cand = nbr[centre, k + iv[I_PROBE_PTR] % nprobe]
                    iv[I_PROBE_PTR] += 1
                    if not active[cand]:
                        worst = -1
                        wq = -1.0
                        for j in range(J):
                            if active[j] and j != centre and st[j, S_QS] > wq:
                                wq = st[j, S_QS]
                                worst = j
                        if worst >= 0:
                            deactivate(worst, st, active, iv)
                            activate(cand, st, active, fv, iv, mat, st[centre, S_QS], 1.0 / k)
                        break
    else:
        sentinel = iv[I_SENTINEL]
        s = st[sentinel, S_QS]
        fv[F_SIGNAL] = s
        if iv[I_SINCE_SWITCH] >= dwell and s < fv[F_HYST] * fv[F_THRESH]:
            # touch-down: back to the on-ground subset around the sentinel
            deactivate(air, st, active, iv)
            iv[I_MODE] = MODE_GROUND
            iv[I_SENTINEL] = -1
            iv[I_SINCE_SWITCH] = 0
            iv[I_NSWITCH] += 1
            # the new on-ground filters start from the sentinel's (on-ground) estimate
            for i in range(4):
                fv[F_XDEV + i] = st[sentinel, S_XPOST + i] - mat[sentinel, i, M_XBAR]
                fv[F_XDEVM + i] = st[sentinel, S_XPRIOR + i] - mat[sentinel, i, M_XBAR]
            _move_to(sentinel, st, active, fv, iv, nbr, vec, mat)
