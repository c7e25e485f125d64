"""Shared pieces of the runtime bank kernel: enums, the packed-buffer layout, small helpers.

The per-tick step is one numba call.  A numba call pays ~40 ns per array argument, so
the runtime packs its data into six buffers instead of ~30 named arrays:

``mat`` (J, 4, MAT_COLS) float, per model, for the *selected* noise entry and weight set:
    [:, :, 0:4] filter_A, [4:6] filter_By, [6] filter_Bu, [7] filter_b,
    [8:10] kalman_gain L, [10:12] C_meas transposed, [12] state part of the LQ gain,
    [13] x̄_j (equilibrium; for the airborne model the nominal static state, used to
    reset it -- its LQ gain is zero), [14:16] of rows 0 and 1: the gain of the
    rattlespace (row 0) and acceleration (row 1) measurement-bias states on the residual.
``vec`` (J, VEC_COLS) float: [0:2] D_meas, [2:6] F^-1 row major, [6] log|F|,
    [7:9] human-filter part of the LQ gain, [9] airborne (1.0/0.0),
    [10] log-likelihood constant -(m/2) log 2π - ½ log|F|, [11:14 + MAX_DELAY] the
    actuator part of the gain: spool estimate, measured force, state w of the flow
    feedforward's rate filter, pending spool commands.
``st`` (J, ST_COLS) float, per-model state (the public (J,) views point into it).
``active`` (J,) bool: the filters that run this tick.
``fv`` float: scalar parameters, then scalar state (incl. the moving bank's tire-contact
    test, F_LOFF..F_LC, the bump-stop input F_BS_*, the estimator monitor F_MON_*, the
    end-stop guard F_GUARD_*), then
    the fuzzy table, the residual-history histogram, the tire-load estimator's rings of
    the last 2Δ+1 rattlespace and acceleration samples and the monitor's window ring, at
    offsets stored in ``iv`` (the rings follow the histogram).
``iv`` int64: integer parameters, then integer state (mode, centre, counters, flags).
``nbr`` (J, n_ground) int64: for on-ground model c, the on-ground models by grid
    distance from c (nbr[c, 0] == c); rows of airborne models are -1.

The per-tick loops run over the ascending list of running filters kept in ``iv``
(maintained by :func:`activate` / :func:`deactivate`), so a tick costs O(k), not O(J).

Everything the kernels touch is preallocated here; the kernels allocate nothing.
"""

from __future__ import annotations

import math
from enum import IntFlag

import numba as nb
import numpy as np

from controller.config import MAX_COMPUTE_DELAY_TICKS
from rig.wire.protocol import Blending

__all__ = ["Blending", "StepFlag"]


class StepFlag(IntFlag):
    """Bits of ``BankRuntime.flags`` after a step.

    NONFINITE_* and DIVERGED (the estimate is unusable) are faults.  DEGRADED is not: the
    innovation statistics say the models do not fit, and the bank runs its conservative
    law (force authority ramped to zero) until they recover (docs/design.md §9)."""

    NONFINITE_INPUT = 1
    NONFINITE_STATE = 2
    NO_RULE_FIRED = 4
    DIVERGED = 8
    DEGRADED = 16


MEAS_DIM = 2            # m, measurement dimension [rattlespace_abs, accel]
Q_MAX = 1.0e12          # likelihood quotients are clamped here (keeps smoothing finite)
QS_INIT = float(MEAS_DIM)   # smoothed q starts at E[q] of a matched filter

# --- mat columns
M_A, M_BY, M_BU, M_B, M_L, M_CT, M_KX, M_XBAR = 0, 4, 6, 7, 8, 10, 12, 13
M_LB = 14           # (2) rows 0 / 1: bias-state gains (rattlespace / acceleration bias)
MAT_COLS = 16
# --- vec columns
V_D, V_FINV, V_LOGDET, V_KF, V_AIR, V_LLC, V_KA = 0, 2, 6, 7, 9, 10, 11
MAX_DELAY = MAX_COMPUTE_DELAY_TICKS   # pending spool commands kept (design.compute_delay_ticks)
VEC_COLS = V_KA + 3 + MAX_DELAY
# --- st columns
S_XPRIOR, S_XPOST, S_Q, S_W, S_P, S_U = 0, 4, 8, 9, 10, 11
S_QS, S_F, S_CONTRIB, S_BAD = 12, 13, 14, 15
S_BR, S_BA = 16, 17     # measurement-bias estimates: rattlespace [m], acceleration [m/s^2]
S_QW = 18               # windowed q (exponential window fuzzy.window_s): fuzzy statistic
ST_COLS = 19

# --- fv: scalar parameters
F_YOFF = 0          # (2) y_offset
F_HAD = 2           # (4) human filter Ad, row major
F_HBD = 6           # (2) human filter Bd
F_STATIC = 8        # static rattlespace M g / K [m]
F_ALPHA = 9         # smoothing factor of q (1 - exp(-dt / tau))
F_PFLOOR = 10       # Bayesian probability floor
F_TFLOOR = 12       # lowest residual threshold (chi-square quantile)
F_QUANT = 14        # threshold quantile
F_FORGET = 15       # 1 / (1 - 1/N) growth of the history increment (exponential window)
F_RECENTRE = 16     # re-centre when qs[best] < ratio * qs[centre]
F_HLO = 17          # histogram lower edge, log10 q
F_HWIDTH = 18       # histogram bin width, decades
# --- fv: scalar state
F_XF = 20           # (2) human-filter states
F_XHAT = 22         # (4) blended posterior (absolute) state estimate
F_XHATM = 26        # (4) blended next prior
F_XINIT = 30        # (4) nominal static state (reset fallback)
F_THRESH = 34       # learnt residual threshold
F_SIGNAL = 35       # smoothed min q of the on-ground set (moving bank)
F_HINC = 36         # current history increment
F_HTOT = 37         # total history weight
F_OUT = 38          # last force reference [N]
F_SCR = 40          # (16) scratch
F_XDEV = 56         # (4) blended posterior deviation from the models' equilibria
F_XDEVM = 60        # (4) blended next-prior deviation (bumpless starts)
# --- fv: spool model of the force path (controller/actuator.py)
F_SDECAY = 64       # e^{-T/tau}
F_SKP = 65          # PI proportional gain [1/N]
F_SFLIM = 66        # force reference limit [N]
F_SOLIM = 67        # spool command limit
F_XV = 68           # spool position estimate
F_PEND = 69         # (MAX_DELAY) spool commands not yet at the valve, newest first
# --- fv: flow feedforward of the force loop (controller/actuator.py FlowFeedforward)
F_FFC = 73          # c, spool per m/s of extension rate at zero load (0 = off)
F_FFA = 74          # a, coefficient of the low-pass on the differentiated LVDT
F_FFB = 75          # b = a / T [1/s]
F_FFSTALL = 76      # stall force A Ps [N]
F_FFFLOOR = 77      # floor of the relative valve pressure drop
F_FFW = 78          # w, state of the rate filter [m/s]; NaN = no reading since reset
# --- fv: tire-contact test of the moving bank (controller/runtime/moving_bank.py)
F_LOFF = 80         # lift-off CUSUM reference: estimated tire load / static load
F_LON = 81          # touch-down CUSUM reference (F_LOFF / hysteresis ratio)
F_LH = 82           # decision threshold of both CUSUMs [load fraction x ticks]
F_LOAD = 83         # estimated tire load / static load (controller/runtime/moving_bank.py)
F_GOFF = 84         # lift-off CUSUM statistic
F_GON = 85          # touch-down CUSUM statistic
F_LINVG = 86        # 1 / g
F_LC = 87           # m / ((M + m) g (Δ T)^2): weight of the rattlespace second difference
# --- fv: bump stops as a known filter input (LVDT frame)
F_BS_K = 88         # stop stiffness [N/m] (0: no stop input)
F_BS_LO = 89        # LVDT reading where the rebound (extension) stop engages [m]
F_BS_HI = 90        # LVDT reading where the compression stop engages [m]
F_BIAS = 91         # (2) blended bias estimates (bumpless starts)
F_QW_ALPHA = 93     # smoothing factor of the fuzzy statistic (1 - exp(-dt / window))
# --- fv: estimator monitor (docs/design.md §9)
F_MON_THR = 94      # degrade when the window sum of min q exceeds this
F_MON_REARM = 95    # re-arm when it stays below this for I_MON_RECOVER ticks
F_MON_SUM = 96      # window sum of min q (state)
F_AUTH = 97         # force authority in [0, 1] (state)
F_AUTH_STEP = 98    # authority change per tick (1 / ramp ticks)
F_UNUSE_R = 99      # unusable: every model's |rattlespace innovation| above this [m]
F_UNUSE_A = 100     # ... or every model's |acceleration innovation| above this [m/s^2]
F_STOP = 101        # bump-stop force of the last tick [N] (read-out)
F_AMEAN = 102       # running mean of the accelerometer reading (its bias) [m/s^2] (state)
F_AMEAN_ALPHA = 103  # weight of the running mean, 1 - exp(-dt / accel_mean_window_s) (0 off)
F_GUARD_W = 104     # end-stop guard: zone width in front of each stop [m] (0: off)
F_GUARD_S = 105     # end-stop guard: factor applied to the force of the last tick (read-out)
FV_HEAD = 106       # the fuzzy table starts here

# --- iv: parameters
I_J, I_G, I_BLEND, I_SINGLE, I_AIR, I_NG, I_K, I_DWELL, I_PROBE = range(9)
I_MON_MAXBAD = 9    # ticks of unusable estimate that set DIVERGED (the monitor window)
I_FALLBACK, I_QGRID, I_WCURVE, I_HIST, I_NB, I_MINLEARN, I_RECOMP, I_NPROBE = range(10, 18)
I_DELAY = 18        # D, compute delay of the design [ticks]
I_LD = 19           # Δ, difference step of the tire-load estimate [ticks]
# --- iv: state
I_MODE = 20         # 0 on ground, 1 airborne (moving bank)
I_CENTRE = 21       # centre of the moving subset
I_SENTINEL = 22     # on-ground filter kept running (zero weight) while airborne
I_SINCE_SWITCH = 23
I_SINCE_RECENTRE = 24
I_PROBE_PTR = 25
I_PROBE_CNT = 26
I_FLAGS = 28
I_NUPD = 29         # filter updates in the last tick
I_NSWITCH = 30      # set switches since reset
I_NLEARN = 31       # history samples learnt
I_NRECENTRE = 32    # re-centres since reset
I_TICK = 33
I_NACT = 34         # number of running filters
I_NLIFT_LOAD = 35   # lift-offs declared by the tire-load CUSUM since reset
I_LPTR = 36         # next write position in the tire-load rings
I_LCNT = 37         # samples in the tire-load rings (saturates at 2Δ+1)
# --- iv: fuzzy statistic and estimator monitor
I_FSTAT = 38        # fuzzy input: FSTAT_RAW (per-tick q, App. A) or FSTAT_RELATIVE
I_MON_N = 39        # monitor window length N [ticks] (0: monitor off)
I_MON_RING = 40     # offset of the monitor's window ring in fv
I_MON_RECOVER = 41  # ticks below the re-arm level needed to re-arm
I_MON_PTR = 42      # next write position in the window ring (state)
I_MON_CNT = 43      # samples in the window (saturates at N) (state)
I_MON_DEG = 44      # 1 while degraded (state)
I_MON_OK = 45       # consecutive ticks below the re-arm level (state)
I_MON_BAD = 46      # consecutive ticks with an unusable estimate (state)
I_MON_NDEG = 47     # degradations since reset (state)
I_MON_DEGTICKS = 48  # ticks spent degraded since reset (state)
IV_ACT = 56         # iv[IV_ACT : IV_ACT + I_NACT]: the running filters, ascending
IV_HEAD = 56        # iv has IV_HEAD + J entries

MODE_GROUND = 0
MODE_AIR = 1

FALLBACK_PASSIVE = 0
FALLBACK_BEST = 1

FSTAT_RAW = 0
FSTAT_RELATIVE = 1



@nb.njit(cache=True, nogil=True)
def firing_weight(q: float, fv: np.ndarray, off_grid: int, off_curve: int, G: int) -> float:
    """Tabulated firing weight at q (linear interpolation, clamped to the universe);
    NaN in the table (no rule fired there) reads as 0."""
    if q <= fv[off_grid]:
        v = fv[off_curve]
    elif q >= fv[off_grid + G - 1]:
        v = fv[off_curve + G - 1]
    else:
        lo = 0
        hi = G - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if fv[off_grid + mid] <= q:
                lo = mid
            else:
                hi = mid
        x0 = fv[off_grid + lo]
        x1 = fv[off_grid + hi]
        y0 = fv[off_curve + lo]
        y1 = fv[off_curve + hi]
        v = y0 + (y1 - y0) * (q - x0) / (x1 - x0)
    if not (v > 0.0):       # NaN or <= 0
        return 0.0
    return min(v, 1.0)


@nb.njit(cache=True, nogil=True)
def activate(j: int, st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
             mat: np.ndarray, qs0: float, p0: float) -> None:
    """Switch filter j on, bumpless: its prior is its own equilibrium plus the current
    blended deviation from equilibrium (the models' equilibria differ -- each secant
    tire spring carries the weight at its own deflection -- so the deviation, not the
    absolute state, is what carries over between models); its bias estimates are the
    blended ones; both smoothed statistics start at ``qs0``."""
    if not active[j]:
        n = iv[I_NACT]
        pos = n
        while pos > 0 and iv[IV_ACT + pos - 1] > j:   # keep the list ascending
            iv[IV_ACT + pos] = iv[IV_ACT + pos - 1]
            pos -= 1
        iv[IV_ACT + pos] = j
        iv[I_NACT] = n + 1
    active[j] = True
    for i in range(4):
        st[j, S_XPRIOR + i] = mat[j, i, M_XBAR] + fv[F_XDEVM + i]
        st[j, S_XPOST + i] = mat[j, i, M_XBAR] + fv[F_XDEV + i]
    st[j, S_BR] = fv[F_BIAS]
    st[j, S_BA] = fv[F_BIAS + 1]
    st[j, S_QS] = qs0
    st[j, S_QW] = qs0
    st[j, S_P] = p0
    st[j, S_Q] = 0.0
    st[j, S_W] = 0.0
    st[j, S_U] = 0.0
    st[j, S_F] = 0.0
    st[j, S_BAD] = 0.0
    st[j, S_CONTRIB] = 0.0


@nb.njit(cache=True, nogil=True)
def stop_guard(fv: np.ndarray, force_n: float, rattlespace_m: float) -> float:
    """The force after the end-stop guard (controller/stop_guard.py): a force toward a
    bump stop fades linearly to 0 over the last ``F_GUARD_W`` metres before it; the
    factor is kept in ``F_GUARD_S``."""
    w = fv[F_GUARD_W]
    s = 1.0
    if w > 0.0:
        if force_n < 0.0:
            s = (fv[F_BS_HI] - rattlespace_m) / w
        elif force_n > 0.0:
            s = (rattlespace_m - fv[F_BS_LO]) / w
        s = min(max(s, 0.0), 1.0)
    fv[F_GUARD_S] = s
    return force_n * s


@nb.njit(cache=True, nogil=True)
def normalise_probabilities(st: np.ndarray, iv: np.ndarray) -> None:
    """Rescale the MMAE probabilities of the running filters to sum 1 (after the running
    set changed: leavers took their probability with them, newcomers brought 1/k)."""
    n = iv[I_NACT]
    total = 0.0
    for a in range(n):
        total += st[iv[IV_ACT + a], S_P]
    for a in range(n):
        j = iv[IV_ACT + a]
        st[j, S_P] = st[j, S_P] / total if total > 0.0 else 1.0 / n


@nb.njit(cache=True, nogil=True)
def deactivate(j: int, st: np.ndarray, active: np.ndarray, iv: np.ndarray) -> None:
    """Switch filter j off: it does no work and contributes zero."""
    if active[j]:
        n = iv[I_NACT]
        pos = 0
        while pos < n and iv[IV_ACT + pos] != j:
            pos += 1
        for i in range(pos, n - 1):
            iv[IV_ACT + i] = iv[IV_ACT + i + 1]
        iv[I_NACT] = n - 1
    active[j] = False
    st[j, S_Q] = 0.0
    st[j, S_W] = 0.0
    st[j, S_P] = 0.0
    st[j, S_U] = 0.0
    st[j, S_F] = 0.0
    st[j, S_CONTRIB] = 0.0
    st[j, S_BAD] = 0.0


@nb.njit(cache=True, nogil=True)
def servo_update(fv: np.ndarray, nd: int, force_ref_n: float, force_meas_n: float,
                 rattlespace_m: float) -> None:
    """Advance the spool model by one tick after the force reference went out:
    s_k = clip(kp (clip(fref) - F_meas) + s_ff), the valve gets s_{k-D}, x̂_v follows it
    (ZOH).  s_ff is the force loop's flow feedforward (``FlowFeedforward.step``), its
    rate-filter state w (F_FFW) advanced here; the caller initialises a NaN w."""
    b = fv[F_FFB]
    rho = fv[F_FFW] + b * rattlespace_m              # filtered rattlespace rate r'
    fv[F_FFW] = (1.0 - fv[F_FFA]) * rho - b * rattlespace_m
    ff = 0.0
    v = -rho                                         # extension rate zs' - zu'
    if v != 0.0 and fv[F_FFC] != 0.0:
        sgn = 1.0 if v > 0.0 else -1.0
        drop = max(1.0 - sgn * force_meas_n / fv[F_FFSTALL], fv[F_FFFLOOR])
        ff = fv[F_FFC] * v / math.sqrt(drop)
    lim_f = fv[F_SFLIM]
    fr = min(max(force_ref_n, -lim_f), lim_f)
    lim = fv[F_SOLIM]
    s = min(max(fv[F_SKP] * (fr - force_meas_n) + ff, -lim), lim)
    if nd == 0:
        applied = s
    else:
        applied = fv[F_PEND + nd - 1]
        for i in range(nd - 1, 0, -1):
            fv[F_PEND + i] = fv[F_PEND + i - 1]
        fv[F_PEND] = s
    a = fv[F_SDECAY]
    fv[F_XV] = a * fv[F_XV] + (1.0 - a) * applied
