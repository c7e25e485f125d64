"""Moving bank supervisor (thesis Ch. VI; Maybeck & Schore's moving-bank MMAE).

The models form a grid (deflection index x tire-damping-scale index, ``grid_index``)
plus the airborne model.  Two sets:

* **on-ground set** -- a moving subset of k = ``moving_bank.active_models`` grid models,
  the k nearest (in grid steps; ties prefer the deflection axis) to the *centre*;
* **airborne set** -- the airborne model, plus one *sentinel*: the last on-ground centre
  keeps running with zero weight ("even if the filter starts running ... the final
  output ... is still zero", Ch. VI), so that the on-ground filters can restart from
  an on-ground estimate at touch-down.

Switched-off filters do no work and contribute zero.

**Tire-load estimate** (:func:`tire_load_update`).  The two masses' momentum balance
gives the tire force without any filter model:  f_t = (M + m)(a + g) + m r'', a = zs''
measured, r = zu - zs the LVDT rattlespace, r'' its central second difference over
Δ = ``load_estimate_window_s`` (5 ticks: noise ~0.06 of the static load with the default
sensors, Δ ticks of lag).  λ = f_t / ((M + m) g) is 1 at rest and 0 with the wheel in
the air.  Why not the filters' own tire deflection x2⁺ (secant force Kt x2⁺): with a
rough-road noise entry (the default, ISO D at 11 m/s) the on-ground filters absorb a
lift-off as a road drop -- x2⁺ follows the truth but so does their residual, q stays
~2-7 and the residual test never fires -- while with a smooth entry they cannot follow
(x2⁺ stays at 0.3-0.5 of the static load in the air); either way one statistic is
blind in one regime.  λ is the same in both.

**Lift-off / touch-down: Page's CUSUM on λ** (a sequential test for a mean shift from
the ground, λ ≈ 1, to the air, λ = 0), with reference λ_off = ``liftoff_load_fraction``
and decision threshold h = λ_off x round(``liftoff_detection_time_s`` / T)::

    on ground:  G_off <- max(0, G_off + λ_off - λ)       lift-off when G_off >= h
    airborne:   G_on  <- max(0, G_on + λ - λ_on)         touch-down when G_on >= h

λ_on = λ_off / ``hysteresis_ratio`` (0.4 with the defaults) is the Schmitt gap: a load
between the two references feeds neither test.  At zero load the lift-off fires after
h / λ_off ticks (8; with the Δ lag ~10-16 ms after the wheel leaves the road).  Short
light-tire phases on a rough road stay below h; a load near zero for ~10 ms or more is
treated as a lift-off (on ISO D at 11 m/s the tire does leave the road now and then).
Each CUSUM starts at 0 when its set takes over.

**Residual test** (the thesis's learnt threshold, kept as a second lift-off test):
s = smoothed min q of the running on-ground filters (EWMA, ``smoothing_time_s``) above
T switches to the airborne set *if the tire is light*, i.e. the lift-off CUSUM already
holds half its evidence (G_off >= h / 2): a residual anomaly at a high load is a
compression peak the secant models do not fit, not a lift-off (on ISO D such peaks
exceeded T several times per 5 s), and a single noisy λ below λ_off is no light tire.
T is *learnt from history*: the ``threshold_quantile`` quantile of s over an exponential
window of ``history_window_s`` (a log-spaced histogram with exponential forgetting),
learnt only while on the ground and settled, and never below the chi-square quantile
-2 ln(1 - quantile) that a matched filter's q (m = 2) exceeds with probability
1 - quantile.  Until enough history is learnt T is that floor.  The residual test
speeds up detection when the residuals do explode (smooth noise entry).  The touch-down
is the load test's alone: after a lift-off the sentinel's q is low in the air with a
rough entry and high for ~50 ms after the landing impact, so a q-based return (the old
``s_sentinel < hysteresis_ratio * T``) came too early or got stuck until the airborne
filter tripped the divergence fault.

    on ground --(dwell elapsed and (G_off >= h or (s > T and G_off >= h/2)))--> airborne
    airborne  --(dwell elapsed and G_on >= h)--> on ground

Not used: a likelihood ratio of the airborne filter against the on-ground ones.  The
airborne filter has no process noise on the relative motion, so its gain is ~0: it is an
open-loop predictor whose q grows to 1e2-1e3 within 10 ms of a bumpless start even in a
genuine flight, so its likelihood says nothing about contact.

Within the on-ground set the subset is re-centred on the best model (min smoothed q) when
qs[best] < RECENTRE_RATIO * qs[centre] and ``dwell_time_s`` has elapsed since the last
re-centre.  So that every grid direction gets explored even with small k (a 9 x 3 grid
and k = 3 would otherwise only ever move along the deflection axis), every probe period
the worst non-centre member is swapped for the next candidate in the centre's
neighbour list (round robin over the next ``nprobe`` nearest).  A newly activated
filter starts bumpless -- at its own equilibrium plus the blended deviation from
equilibrium (:func:`controller.runtime.kernels.activate`) -- with the centre's smoothed q; at
touch-down the blend is the airborne filter's, so the returning on-ground filters start
from the sentinel's deviation instead (an on-ground view; the airborne predictor's
relative states have drifted).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from controller.runtime import kernels as kern
from controller.runtime.kernels import activate, deactivate, normalise_probabilities

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
    "tire_load_update",
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


def neighbour_table(grid_index: NDArray[np.int64], airborne: NDArray[np.bool_],
                    layer: NDArray[np.int64] | None = None) -> NDArray[np.int64]:
    """(J, n_ground): for each on-ground model c, the on-ground models ordered by grid
    distance from c (Euclidean in index steps; ties: smaller damping-index offset first,
    then model index); with sprung-mass ``layer``s, c's own layer first, then the nearer
    layers.  Row c starts with c itself.  Airborne rows are -1."""
    J = int(grid_index.shape[0])
    ground = np.flatnonzero(~np.asarray(airborne, dtype=bool))
    lay = np.zeros(J, dtype=np.int64) if layer is None else np.asarray(layer, dtype=np.int64)
    out = -np.ones((J, ground.size), dtype=np.int64)
    gi = np.asarray(grid_index, dtype=np.int64)[ground]
    gl = lay[ground]
    for row, c in enumerate(ground):
        dd = gi[:, 0] - gi[row, 0]
        ds = gi[:, 1] - gi[row, 1]
        # lexsort: the last key is the primary one
        order = np.lexsort((ground, np.abs(ds), dd * dd + ds * ds, np.abs(gl - gl[row])))
        out[c, :] = ground[order]
    return out


# ---------------------------------------------------------------------------- history


@nb.njit(cache=True, nogil=True)
def history_add(fv: np.ndarray, iv: np.ndarray, s: float) -> None:
    """Add one sample of the switching signal to the exponentially forgotten histogram."""
    off = iv[kern.I_HIST]
    nb_ = iv[kern.I_NB]
    inc = fv[kern.F_HINC] * fv[kern.F_FORGET]
    if inc > 1e100:                    # rescale everything (rare): keeps the numbers finite
        scale = 1.0 / inc
        for b in range(nb_):
            fv[off + b] *= scale
        fv[kern.F_HTOT] *= scale
        inc = 1.0
    fv[kern.F_HINC] = inc
    b = int((math.log10(s) - fv[kern.F_HLO]) / fv[kern.F_HWIDTH]) if s > 0.0 else 0
    b = min(max(b, 0), nb_ - 1)
    fv[off + b] += inc
    fv[kern.F_HTOT] += inc
    iv[kern.I_NLEARN] += 1


@nb.njit(cache=True, nogil=True)
def history_quantile(fv: np.ndarray, iv: np.ndarray, quantile: float) -> float:
    """The ``quantile`` of the learnt history (log-linear inside the bin)."""
    off = iv[kern.I_HIST]
    nb_ = iv[kern.I_NB]
    target = quantile * fv[kern.F_HTOT]
    cum = 0.0
    for b in range(nb_):
        c = fv[off + b]
        if c > 0.0 and cum + c >= target:
            frac = (target - cum) / c
            return 10.0 ** (fv[kern.F_HLO] + (b + frac) * fv[kern.F_HWIDTH])
        cum += c
    return 10.0 ** (fv[kern.F_HLO] + nb_ * fv[kern.F_HWIDTH])


# ---------------------------------------------------------------------------- subset moves


@nb.njit(cache=True, nogil=True)
def _move_to(centre: int, st: np.ndarray, active: np.ndarray, fv: np.ndarray,
             iv: np.ndarray, nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray) -> None:
    """Active set := the k nearest grid models of ``centre`` (no airborne model); the
    models that stay keep their probability, newcomers start at 1/k, then the
    probabilities are rescaled to sum 1 over the new set."""
    k = iv[kern.I_K]
    ng = iv[kern.I_NG]
    J = st.shape[0]
    qs0 = st[centre, kern.S_QS]
    p0 = 1.0 / k
    for j in range(J):                     # switch off what is not in the new subset
        if active[j]:
            keep = False
            if vec[j, kern.V_AIR] == 0.0:
                for i in range(min(k, ng)):
                    if nbr[centre, i] == j:
                        keep = True
            if not keep:
                deactivate(j, st, active, iv)
    for i in range(min(k, ng)):
        j = nbr[centre, i]
        if not active[j]:
            activate(j, st, active, fv, iv, mat, qs0, p0)
    normalise_probabilities(st, iv)
    iv[kern.I_CENTRE] = centre
    iv[kern.I_SINCE_RECENTRE] = 0
    iv[kern.I_PROBE_PTR] = 0
    iv[kern.I_PROBE_CNT] = 0


@nb.njit(cache=True, nogil=True)
def enter_moving(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
                 nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray, centre: int) -> None:
    """Start the moving bank on the ground, centred on ``centre``."""
    iv[kern.I_MODE] = kern.MODE_GROUND
    iv[kern.I_SENTINEL] = -1
    iv[kern.I_SINCE_SWITCH] = 0
    fv[kern.F_GOFF] = 0.0
    fv[kern.F_GON] = 0.0
    fv[kern.F_LOAD] = 1.0
    iv[kern.I_LCNT] = 0                 # the rings were not fed outside the moving mode
    iv[kern.I_LPTR] = 0
    _move_to(centre, st, active, fv, iv, nbr, vec, mat)


@nb.njit(cache=True, nogil=True)
def tire_load_update(fv: np.ndarray, iv: np.ndarray, rattlespace_m: float,
                     accel_mps2: float) -> float:
    """Feed one sample to the tire-load estimate and return it (also in ``fv[kern.F_LOAD]``).

    Momentum balance of the two masses, model-free: the tire force is
    f_t = M (zs'' + g) + m (zu'' + g) = (M + m)(a + g) + m r'' with r = zu - zs the
    rattlespace (compression positive) and a = zs''.  r'' is the second difference over
    Δ ticks, centred on tick k - Δ, so the estimate is that of tick k - Δ; as a fraction
    of the static load (M + m) g:

        λ_k = 1 + a_{k-Δ} / g + m (r_k - 2 r_{k-Δ} + r_{k-2Δ}) / ((M + m) g (Δ T)^2)

    1.0 (no evidence) until 2Δ + 1 samples are in.  Allocation-free: two rings of 2Δ + 1
    samples in ``fv`` after the residual histogram."""
    d = iv[kern.I_LD]
    n = 2 * d + 1
    off = iv[kern.I_HIST] + iv[kern.I_NB]         # r ring, then a ring, after the histogram
    p = iv[kern.I_LPTR]
    fv[off + p] = rattlespace_m
    fv[off + n + p] = accel_mps2
    cnt = iv[kern.I_LCNT]
    if cnt < n:
        cnt += 1
        iv[kern.I_LCNT] = cnt
    load = 1.0
    if cnt >= n:
        i1 = (p - d) % n
        i2 = (p + 1) % n                 # == p - 2Δ (mod n)
        load = 1.0 + fv[off + n + i1] * fv[kern.F_LINVG] \
            + fv[kern.F_LC] * (rattlespace_m - 2.0 * fv[off + i1] + fv[off + i2])
    iv[kern.I_LPTR] = (p + 1) % n
    fv[kern.F_LOAD] = load
    return load


@nb.njit(cache=True, nogil=True)
def supervise(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
              nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray) -> None:
    """After a tick: learn the threshold, run the tire-contact CUSUMs, switch sets,
    re-centre or probe (for next tick)."""
    J = st.shape[0]
    dwell = iv[kern.I_DWELL]
    iv[kern.I_SINCE_SWITCH] += 1
    iv[kern.I_SINCE_RECENTRE] += 1
    air = iv[kern.I_AIR]
    if iv[kern.I_MODE] == kern.MODE_GROUND:
        best = -1
        s = np.inf
        for a in range(iv[kern.I_NACT]):
            j = iv[kern.IV_ACT + a]
            if vec[j, kern.V_AIR] == 0.0 and st[j, kern.S_QS] < s:
                s = st[j, kern.S_QS]
                best = j
        fv[kern.F_SIGNAL] = s
        centre = iv[kern.I_CENTRE]
        load = fv[kern.F_LOAD]
        g = fv[kern.F_GOFF] + (fv[kern.F_LOFF] - load)
        fv[kern.F_GOFF] = g if g > 0.0 else 0.0          # also 0 for a NaN load
        settled = iv[kern.I_SINCE_SWITCH] >= dwell
        if settled:
            history_add(fv, iv, s)
            n_learnt = iv[kern.I_NLEARN]
            if n_learnt >= iv[kern.I_MINLEARN] and n_learnt % iv[kern.I_RECOMP] == 0:
                fv[kern.F_THRESH] = max(history_quantile(fv, iv, fv[kern.F_QUANT]),
                                        fv[kern.F_TFLOOR])
        by_load = fv[kern.F_GOFF] >= fv[kern.F_LH]
        by_residual = s > fv[kern.F_THRESH] and fv[kern.F_GOFF] >= 0.5 * fv[kern.F_LH]
        if air >= 0 and settled and (by_load or by_residual):
            # lift-off: the airborne set takes over; the centre stays as zero-weight sentinel
            for j in range(J):
                if active[j] and j != centre:
                    deactivate(j, st, active, iv)
            activate(air, st, active, fv, iv, mat, st[centre, kern.S_QS], 1.0)
            st[centre, kern.S_P] = 0.0
            st[centre, kern.S_W] = 0.0
            iv[kern.I_SENTINEL] = centre
            iv[kern.I_MODE] = kern.MODE_AIR
            iv[kern.I_SINCE_SWITCH] = 0
            iv[kern.I_NSWITCH] += 1
            if by_load:
                iv[kern.I_NLIFT_LOAD] += 1
            fv[kern.F_GON] = 0.0
            return
        if best >= 0 and best != centre and iv[kern.I_SINCE_RECENTRE] >= dwell \
                and st[best, kern.S_QS] < fv[kern.F_RECENTRE] * st[centre, kern.S_QS]:
            _move_to(best, st, active, fv, iv, nbr, vec, mat)
            iv[kern.I_NRECENTRE] += 1
            return
        nprobe = iv[kern.I_NPROBE]
        if nprobe > 0 and iv[kern.I_K] >= 2:
            iv[kern.I_PROBE_CNT] += 1
            if iv[kern.I_PROBE_CNT] >= iv[kern.I_PROBE]:
                iv[kern.I_PROBE_CNT] = 0
                k = iv[kern.I_K]
                for _ in range(nprobe):           # next candidate that is not running
                    cand = nbr[centre, k + iv[kern.I_PROBE_PTR] % nprobe]
                    iv[kern.I_PROBE_PTR] += 1
                    if not active[cand]:
                        worst = -1
                        wq = -1.0
                        for j in range(J):
                            if active[j] and j != centre and st[j, kern.S_QS] > wq:
                                wq = st[j, kern.S_QS]
                                worst = j
                        if worst >= 0:
                            deactivate(worst, st, active, iv)
                            activate(cand, st, active, fv, iv, mat, st[centre, kern.S_QS], 1.0 / k)
                            normalise_probabilities(st, iv)
                        break
    else:
        sentinel = iv[kern.I_SENTINEL]
        fv[kern.F_SIGNAL] = st[sentinel, kern.S_QS]
        g = fv[kern.F_GON] + (fv[kern.F_LOAD] - fv[kern.F_LON])
        fv[kern.F_GON] = g if g > 0.0 else 0.0
        if iv[kern.I_SINCE_SWITCH] >= dwell and fv[kern.F_GON] >= fv[kern.F_LH]:
            # touch-down: back to the on-ground subset around the sentinel
            deactivate(air, st, active, iv)
            iv[kern.I_MODE] = kern.MODE_GROUND
            iv[kern.I_SENTINEL] = -1
            iv[kern.I_SINCE_SWITCH] = 0
            iv[kern.I_NSWITCH] += 1
            fv[kern.F_GOFF] = 0.0
            # the new on-ground filters start from the sentinel's (on-ground) estimate
            for i in range(4):
                xbar = mat[sentinel, i, kern.M_XBAR]
                fv[kern.F_XDEV + i] = st[sentinel, kern.S_XPOST + i] - xbar
                fv[kern.F_XDEVM + i] = st[sentinel, kern.S_XPRIOR + i] - xbar
            fv[kern.F_BIAS] = st[sentinel, kern.S_BR]
            fv[kern.F_BIAS + 1] = st[sentinel, kern.S_BA]
            # the sentinel (kept out of the blending while airborne, p = 0) rejoins the
            # on-ground set like a newcomer: the set restarts from uniform probabilities
            st[sentinel, kern.S_P] = 1.0 / iv[kern.I_K]
            _move_to(sentinel, st, active, fv, iv, nbr, vec, mat)
