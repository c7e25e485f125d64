"""Runtime step of the LQG bank (thesis Ch. III, IV, VI, App. A): one numba call per tick.

Per tick, with y = [rattlespace + M g / K, accel - running mean of accel] and
u = the measured actuator force + the bump-stop force computed from the rattlespace
reading (docs/design.md §9.1, §9.2):

    r_j  = y - b⁻_j - C_j x⁻_j - D_j u - y_offset         (3.9, b_j: measurement biases)
    q_j  = r_j' F_j^-1 r_j                                (4.8, the likelihood quotient)
    x⁺_j = x⁻_j + L_j r_j                                 (3.5, steady-state gain)
    x⁻_j <- A_j x⁻_j + By_j (y - b⁻_j) + Bu_j u + b_j     (fused 3.5 + 3.7, selected noise entry)
    b_j  <- b_j + Lb_j r_j                                (random-walk bias states)
    u_j  = -K_w,j [x⁺_j - x̄_j; x_f; x̂_v; F; w; s_pending]   (F the load-cell force; 0 airborne)
    x_f  <- Ad x_f + Bd accel                             (F(s); u_j uses x_f before the update)
    x̂_v, w, s_pending <- spool model (controller/actuator.py) driven by the blended output
                         and the rattlespace (flow feedforward of the force loop)

The actuator part of the gain (spool estimate x̂_v, measured force u, the state w of the
force loop's rate filter, the D spool commands still on their way to the valve) is zero
for ``design.actuator_model = "ideal"``.

then the model forces are blended: FUZZY -- firing weight f_j = tabulated App. A curve at
the fuzzy statistic (``fuzzy.statistic``: "relative" = 2 q̄_j / min_k q̄_k with q̄ the
exponentially windowed q, so the best model always fires; "raw" = q_j, the thesis),
normalised over the contributing models (if none fires: ``no_fire_fallback``,
"passive" = 0 N or "best_model" = min statistic, and ``StepFlag.NO_RULE_FIRED``); BAYES --
MMAE probabilities (:mod:`controller.runtime.bayes`); MOVING -- fuzzy within the moving subset
(:mod:`controller.runtime.moving_bank`); LQG -- one model, the plain LQG.  The blended force is
multiplied by the force authority of the estimator monitor (:mod:`controller.monitor`:
the window sum of min q against its chi-square levels; DEGRADED ramps it to 0, re-arming
ramps it back) and by that of the stop-contact monitor (:mod:`controller.stop_contact`:
the LVDT reading's contact time with the bump stops over an exponential window against a
budget; STOP_DEGRADED ramps it to ``safety.stop_contact_authority``), then by the end-stop
guard (:mod:`controller.stop_guard`: a force toward a bump stop fades to 0 over
``design.stop_guard_m`` before it).

Bayesian probabilities, raw firing weights and smoothed q are kept for every running
filter in every mode (telemetry; a switch of blending starts warm).

Faults (never raised): a non-finite input returns 0.0 with NONFINITE_INPUT and leaves
the state untouched.  A filter whose q, estimate or force becomes non-finite (huge
inputs can overflow) is reset to its equilibrium plus the blended deviation of the
healthy filters (see :func:`controller.runtime.kernels.activate`) and NONFINITE_STATE is set; a
non-finite blended force returns 0.0.  Every contributing model's innovation beyond a
sensor's range for a whole monitor window sets DIVERGED (the estimate is unusable: a
fault for the loop); DEGRADED is not a fault.  q is clamped to ``Q_MAX``.
"""

from __future__ import annotations

import functools
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from controller.arrays import FloatArray
from controller.artifact import Design
from controller.config import (
    RigConfig,
    default_config,
    layer_config,
    layer_grid,
    layer_params,
    layer_tire_scales,
    parse_config,
)
from controller.mass_estimator import (
    ME_CEST,
    ME_EST,
    ME_KEST,
    ME_NUPD,
    ME_SETTLE,
    ME_SIZE,
    mass_estimator_parameters,
)
from controller.monitor import MonitorSettings, monitor_settings
from controller.plant import static_tire_deflection_m
from controller.ride_height import ride_height_settings
from controller.road_noise import nearest_noise_entry
from controller.road_preview import (
    CLAMP_TRUST_WINDOW_S,
    RoadPreview,
    cached_road_preview,
    clamp_force_bounds_n,
    predicted_peak_m,
)
from controller.runtime.bayes import bayes_update, log_likelihood_constant
from controller.runtime.compiled import direct_call
from controller.runtime.kernels import (
    F_ALPHA,
    F_AMEAN,
    F_AMEAN_ALPHA,
    F_AUTH,
    F_AUTH_STEP,
    F_BIAS,
    F_BS_HI,
    F_BS_K,
    F_BS_LO,
    F_FFA,
    F_FFB,
    F_FFC,
    F_FFFLOOR,
    F_FFSTALL,
    F_FFW,
    F_FORGET,
    F_GOFF,
    F_GON,
    F_GUARD_LEAD,
    F_GUARD_S,
    F_GUARD_V0,
    F_GUARD_W,
    F_HAD,
    F_HBD,
    F_HINC,
    F_HLO,
    F_HTOT,
    F_HWIDTH,
    F_LC,
    F_LH,
    F_LHYST,
    F_LINVG,
    F_LOAD,
    F_LOFF,
    F_LON,
    F_LWC,
    F_LWK,
    F_LWT,
    F_ME,
    F_MES,
    F_MON_REARM,
    F_MON_SUM,
    F_MON_THR,
    F_OUT,
    F_PEND,
    F_PFLOOR,
    F_PVC_AIRW,
    F_PVC_ALPHA,
    F_PVC_BRAKE,
    F_PVC_FMAX,
    F_PVC_FMIN,
    F_PVC_FOR,
    F_PVC_MS,
    F_PVC_PRED,
    F_PVC_TRUST2,
    F_QUANT,
    F_QW_ALPHA,
    F_RECENTRE,
    F_RH,
    F_RH_ALPHA,
    F_RH_CENTRE,
    F_RH_CLEAR,
    F_RH_WARN,
    F_SB,
    F_SB_DF,
    F_SB_V,
    F_SC_AUTH,
    F_SC_BAND,
    F_SC_BUDGET,
    F_SC_DECAY,
    F_SC_FLOOR,
    F_SC_REARM,
    F_SC_TICK,
    F_SC_TIME,
    F_SCR,
    F_SDECAY,
    F_SFLIM,
    F_SIGNAL,
    F_SKP,
    F_SOLIM,
    F_STATIC,
    F_STOP,
    F_TFLOOR,
    F_THRESH,
    F_TS,
    F_TS_BETA,
    F_TS_ENV,
    F_TS_ON,
    F_UNUSE_A,
    F_UNUSE_R,
    F_WH,
    F_WHS,
    F_XDEV,
    F_XDEVM,
    F_XF,
    F_XHAT,
    F_XHATM,
    F_XINIT,
    F_XV,
    F_YOFF,
    FALLBACK_BEST,
    FALLBACK_PASSIVE,
    FSTAT_RAW,
    FSTAT_RELATIVE,
    FV_HEAD,
    I_AIR,
    I_BLEND,
    I_CENTRE,
    I_DELAY,
    I_DWELL,
    I_FALLBACK,
    I_FLAGS,
    I_FSTAT,
    I_G,
    I_GUARD_LEAD_TICKS,
    I_GUARD_TICKS,
    I_HIST,
    I_J,
    I_K,
    I_LAYER,
    I_LAYER0,
    I_LCAND,
    I_LCNT,
    I_LD,
    I_LDWELL,
    I_LPTR,
    I_LSINCE,
    I_MINLEARN,
    I_MODE,
    I_MON_BAD,
    I_MON_CNT,
    I_MON_DEG,
    I_MON_DEGTICKS,
    I_MON_MAXBAD,
    I_MON_N,
    I_MON_NDEG,
    I_MON_OK,
    I_MON_PTR,
    I_MON_RECOVER,
    I_MON_RING,
    I_NACT,
    I_NB,
    I_NG,
    I_NLAYER,
    I_NLAYERSW,
    I_NLEARN,
    I_NLIFT_LOAD,
    I_NPROBE,
    I_NRECENTRE,
    I_NSWITCH,
    I_NTIRE,
    I_NUPD,
    I_PROBE,
    I_PROBE_CNT,
    I_PROBE_PTR,
    I_PVCALL,
    I_PVCHECKED,
    I_PVCLAMP,
    I_PVCLAMP_TICKS,
    I_QGRID,
    I_RECOMP,
    I_RH_OFF,
    I_SB_TICKS,
    I_SC_DEG,
    I_SC_DEGTICKS,
    I_SC_EPISODES,
    I_SC_GAP,
    I_SC_NDEG,
    I_SC_OK,
    I_SC_ON,
    I_SC_QUIET,
    I_SC_RECOVER,
    I_SC_TICKS,
    I_SENTINEL,
    I_SINCE_RECENTRE,
    I_SINCE_SWITCH,
    I_SINGLE,
    I_SINGLE0,
    I_TICK,
    I_WCURVE,
    IV_ACT,
    IV_HEAD,
    M_A,
    M_B,
    M_BU,
    M_BY,
    M_CT,
    M_KC,
    M_KX,
    M_L,
    M_LB,
    M_XBAR,
    MAT_COLS,
    MAX_DELAY,
    MEAS_DIM,
    MODE_AIR,
    MODE_GROUND,
    PVC_RING,
    Q_MAX,
    QS_INIT,
    S_BA,
    S_BAD,
    S_BR,
    S_CONTRIB,
    S_F,
    S_P,
    S_Q,
    S_QS,
    S_QW,
    S_U,
    S_W,
    S_XPOST,
    S_XPRIOR,
    ST_COLS,
    V_AIR,
    V_D,
    V_FINV,
    V_KA,
    V_KAC,
    V_KF,
    V_KFC,
    V_LAYER,
    V_LLC,
    V_LOGDET,
    V_LOGP,
    V_YSTAT,
    VEC_COLS,
    Blending,
    StepFlag,
    activate,
    deactivate,
    degrade_or_rearm,
    firing_weight,
    mass_estimate,
    mass_estimate_reset,
    ramp_authority,
    ride_height,
    servo_update,
    stop_barrier,
    stop_contact,
    stop_guard,
    travel_comfort_share,
    wheel_hop_reset,
    wheel_hop_track,
)
from controller.runtime.layout import SlotValue
from controller.runtime.mass_layers import (
    gather_running_layer,
    layer_table,
    mass_schedule,
    running_layer_rows,
)
from controller.runtime.moving_bank import (
    HIST_BINS,
    HIST_HI_LOG10,
    HIST_LO_LOG10,
    HIST_RECOMPUTE_TICKS,
    MAX_PROBE_CANDIDATES,
    RECENTRE_RATIO,
    chi2_threshold_floor,
    enter_moving,
    neighbour_table,
    supervise,
    tire_load_update,
)
from controller.stop_barrier import BARRIER_SIZE, braking_force_n
from controller.stop_barrier import stop_barrier as stop_barrier_parameters
from controller.stop_contact import StopContactSettings, stop_contact_settings
from controller.travel_schedule import SCHEDULE_SIZE, THRESHOLDS, travel_schedule
from controller.wheel_hop import (
    WH_SIZE,
    WHS_HZ,
    WHS_NUPD,
    WHS_SCALE,
    passive_wheel_hop_hz,
    wheel_hop_tracker_parameters,
)

__all__ = ["BankRuntime", "Blending", "RunningModels", "StepFlag", "config_of",
           "default_single_model"]

#: sprung-mass layers: another layer must be preferred this long in a row [s] ...
LAYER_DWELL_S = 1.0
#: ... and left for one nearer the estimate by more than this in log mass (about 2 %)
LAYER_HYSTERESIS = 0.02


_FUZZY = int(Blending.FUZZY)
_BAYES = int(Blending.BAYES)
_MOVING = int(Blending.MOVING)
_LQG = int(Blending.LQG)
_NONFINITE_INPUT = int(StepFlag.NONFINITE_INPUT)
_NONFINITE_STATE = int(StepFlag.NONFINITE_STATE)
_NO_RULE_FIRED = int(StepFlag.NO_RULE_FIRED)
_DIVERGED = int(StepFlag.DIVERGED)
_DEGRADED = int(StepFlag.DEGRADED)


_SIG_STEP = nb.float64(nb.float64[:, :, ::1], nb.float64[:, ::1], nb.float64[:, ::1],
                       nb.boolean[::1], nb.float64[::1], nb.int64[::1], nb.int64[:, ::1],
                       nb.float64, nb.float64, nb.float64)
_SIG_TICK = nb.float64(nb.float64[:, :, ::1], nb.float64[:, ::1], nb.float64[:, ::1],
                       nb.boolean[::1], nb.float64[::1], nb.int64[::1], nb.int64[:, ::1],
                       nb.float64, nb.float64, nb.float64, nb.float64[:, ::1],
                       nb.boolean[::1], nb.int64[::1])
#: :data:`_SIG_TICK` and the road preview (:func:`bank_tick_preview`): the predictor's
#: ``rows`` (L, P, 4), ``ticks`` (P,), ``impulse`` (L, H), ``force_rows`` (L, P),
#: ``brake_rows`` (L, P),
#: ``trigger_m`` (L,), ``edge_trigger_m``, the tick the running layer is trusted from,
#: the road velocity ring and the window's start in it
_SIG_TICK_PREVIEW = nb.float64(*_SIG_TICK.args, nb.float64[:, :, ::1], nb.int64[::1],
                               nb.float64[:, ::1], nb.float64[:, ::1], nb.float64[:, ::1],
                               nb.float64[::1],
                               nb.float64, nb.int64, nb.float64, nb.int64,
                               nb.float64[::1], nb.int64)
#: :data:`_SIG_TICK` and the stop clamp with the road at rest (:func:`bank_tick_at_rest`):
#: the predictor's ``rows``, ``ticks``, ``impulse``, ``brake_rows``, the clamp's distance
#: and points, and a road velocity array with the window's start in it (no samples: the
#: road at rest)
_SIG_TICK_AT_REST = nb.float64(*_SIG_TICK.args, nb.float64[:, :, ::1], nb.int64[::1],
                               nb.float64[:, ::1], nb.float64[:, ::1], nb.float64, nb.int64,
                               nb.float64[::1], nb.int64)
_SIG_CFG = nb.void(nb.float64[:, :, ::1], nb.float64[:, ::1], nb.float64[:, ::1],
                   nb.boolean[::1], nb.float64[::1], nb.int64[::1], nb.int64[:, ::1], nb.int64)


#: the stop clamp predicts with the on-ground model only while the airborne model's
#: weight in the blend is at most this (:func:`_clamp_check`)
CLAMP_AIRBORNE_WEIGHT = 0.01

#: :attr:`BankRuntime._trusted_from_tick` of the governed comfort set: no tick
_NEVER_TRUSTED = 2 ** 62


# ============================================================================ kernels


@nb.njit(cache=True, nogil=True)
def _monitor(fv: np.ndarray, iv: np.ndarray, q_min: float, e_min: float) -> int:
    """The estimator monitor, once per tick after the filters (docs/design.md §9).

    Consistency: the sum of the bank's smallest q over the last N ticks (a ring in
    ``fv``; after a reset the first N ticks are skipped -- the filters start at the
    models' equilibria and their first innovations measure the start, not the models)
    against ``F_MON_THR``; above it the bank degrades (force authority ramps to
    0, DEGRADED), and re-arms after ``I_MON_RECOVER`` consecutive ticks below
    ``F_MON_REARM``.  Usability: every contributing model's innovation beyond a sensor's
    range (``e_min`` > 1) for ``I_MON_MAXBAD`` consecutive ticks sets DIVERGED.
    Returns the flag bits."""
    flags = 0
    n = iv[I_MON_N]
    if n > 0 and iv[I_MON_CNT] < 0:     # settling after a reset: the first window is skipped
        iv[I_MON_CNT] += 1
    elif n > 0:
        s = q_min if q_min < Q_MAX else Q_MAX
        ring = iv[I_MON_RING]
        p = iv[I_MON_PTR]
        old = fv[ring + p]
        fv[ring + p] = s
        cnt = iv[I_MON_CNT]
        if cnt < n:
            cnt += 1
            iv[I_MON_CNT] = cnt
            fv[F_MON_SUM] += s
        else:
            fv[F_MON_SUM] += s - old
        p += 1
        if p >= n:              # once per window: the exact sum (no running-sum drift)
            p = 0
            tot = 0.0
            for i in range(n):
                tot += fv[ring + i]
            fv[F_MON_SUM] = tot
        iv[I_MON_PTR] = p
        if cnt >= n:
            degrade_or_rearm(iv, I_MON_DEG, I_MON_OK, I_MON_NDEG, I_MON_RECOVER,
                             fv[F_MON_SUM], fv[F_MON_THR], fv[F_MON_REARM], True)
        if e_min > 1.0:
            iv[I_MON_BAD] += 1
            if iv[I_MON_BAD] >= iv[I_MON_MAXBAD]:
                flags |= _DIVERGED
        else:
            iv[I_MON_BAD] = 0
    degraded = iv[I_MON_DEG] != 0
    if degraded:
        flags |= _DEGRADED
        iv[I_MON_DEGTICKS] += 1
    ramp_authority(fv, F_AUTH, degraded, 0.0)
    return flags


# bank_step is composed of the small helpers below.  They are inlined into it at numba IR
# level (``inline="always"``) and bank_step is compiled without the numba runtime
# (``_nrt=False``, as numba's own allocation-free library helpers are): without the runtime
# it cannot allocate -- a change that would allocate fails to compile -- and the array
# arguments passed to the inlined helpers carry no reference counting (with the runtime,
# every inlined call increfs and decrefs its array arguments: 13-19 % of the kernel time).
# ``python -m bench controller`` and tests/test_bank.py::test_no_allocation_per_tick guard both.


@nb.njit(cache=True, nogil=True, inline="always")
def _measurements(fv: np.ndarray, rattlespace_m: float, accel_mps2: float,
                  force_meas_n: float) -> tuple[float, float, float]:
    """The filters' known input and measurements of this tick: u_in = load-cell force plus
    the bump-stop force from the LVDT reading [N], y0 = absolute rattlespace [m], y1 =
    acceleration minus its running mean (the accelerometer's bias) when enabled [m/s^2]."""
    f_stop = 0.0
    if rattlespace_m > fv[F_BS_HI]:
        f_stop = fv[F_BS_K] * (rattlespace_m - fv[F_BS_HI])
    elif rattlespace_m < fv[F_BS_LO]:
        f_stop = fv[F_BS_K] * (rattlespace_m - fv[F_BS_LO])
    fv[F_STOP] = f_stop
    y1 = accel_mps2
    if fv[F_AMEAN_ALPHA] > 0.0:
        fv[F_AMEAN] += fv[F_AMEAN_ALPHA] * (accel_mps2 - fv[F_AMEAN])
        y1 = accel_mps2 - fv[F_AMEAN]
    return force_meas_n + f_stop, rattlespace_m + fv[F_STATIC], y1


@nb.njit(cache=True, nogil=True, inline="always")
def _filter_update(j: int, mat: np.ndarray, vec: np.ndarray, st: np.ndarray,
                   fv: np.ndarray, nd: int, u_in: float, y0: float, y1: float,
                   force_meas_n: float, xf0: float, xf1: float, comfort: float
                   ) -> tuple[float, float, float, float, float, float]:
    """Measurement and time update of filter j and its LQ control (``comfort``: the travel
    schedule's comfort share, 0 = the selected gain only); the posterior goes to
    ``fv[F_SCR:+4]``, the next prior to ``fv[F_SCR+4:+8]`` until accepted.  Returns the
    likelihood quotient q (NaN when any result is not finite: the caller rejects the
    update), the innovation (r0 [m], r1 [m/s^2]), the updated biases and the control u."""
    y0j = y0 - st[j, S_BR] + vec[j, V_YSTAT]    # about the model's own static position
    y1j = y1 - st[j, S_BA]
    r0 = y0j - fv[F_YOFF] - vec[j, V_D] * u_in
    r1 = y1j - fv[F_YOFF + 1] - vec[j, V_D + 1] * u_in
    for i in range(4):
        xm = st[j, S_XPRIOR + i]
        r0 -= mat[j, i, M_CT] * xm
        r1 -= mat[j, i, M_CT + 1] * xm
    q = r0 * (vec[j, V_FINV] * r0 + vec[j, V_FINV + 1] * r1) \
        + r1 * (vec[j, V_FINV + 2] * r0 + vec[j, V_FINV + 3] * r1)
    ok = not math.isnan(q)
    for i in range(4):
        acc = mat[j, i, M_BY] * y0j + mat[j, i, M_BY + 1] * y1j + mat[j, i, M_BU] * u_in \
            + mat[j, i, M_B]
        for k in range(4):
            acc += mat[j, i, M_A + k] * st[j, S_XPRIOR + k]
        xp = st[j, S_XPRIOR + i] + mat[j, i, M_L] * r0 + mat[j, i, M_L + 1] * r1
        fv[F_SCR + i] = xp
        fv[F_SCR + 4 + i] = acc
        if not (math.isfinite(xp) and math.isfinite(acc)):
            ok = False
    b_r = st[j, S_BR] + mat[j, 0, M_LB] * r0 + mat[j, 0, M_LB + 1] * r1
    b_a = st[j, S_BA] + mat[j, 1, M_LB] * r0 + mat[j, 1, M_LB + 1] * r1
    if not (math.isfinite(b_r) and math.isfinite(b_a)):
        ok = False
    u = 0.0
    if vec[j, V_AIR] == 0.0:
        u = _lq_force(j, mat, vec, fv, nd, M_KX, V_KF, V_KA, force_meas_n, xf0, xf1)
        if comfort > 0.0:       # travel schedule: the comfort law's share (§12)
            u += comfort * (_lq_force(j, mat, vec, fv, nd, M_KC, V_KFC, V_KAC, force_meas_n,
                                   xf0, xf1) - u)
        if not math.isfinite(u):
            ok = False
    return (q if ok else np.nan), r0, r1, b_r, b_a, u


@nb.njit(cache=True, nogil=True, inline="always")
def _lq_force(j: int, mat: np.ndarray, vec: np.ndarray, fv: np.ndarray, nd: int, kx: int,
              kf: int, ka: int, force_meas_n: float, xf0: float, xf1: float) -> float:
    """Model j's LQ force [N] with the gain in slots ``kx`` (mat, state part), ``kf``
    (vec, human filter) and ``ka`` (vec, actuator), on the posterior in ``fv[F_SCR:+4]``."""
    u = -(vec[j, kf] * xf0 + vec[j, kf + 1] * xf1)
    u -= vec[j, ka] * fv[F_XV] + vec[j, ka + 1] * force_meas_n + vec[j, ka + 2] * fv[F_FFW]
    for i in range(nd):
        u -= vec[j, ka + 3 + i] * fv[F_PEND + i]
    for i in range(4):
        u -= mat[j, i, kx] * (fv[F_SCR + i] - mat[j, i, M_XBAR])
    return u


@nb.njit(cache=True, nogil=True, inline="always")
def _accept(j: int, st: np.ndarray, fv: np.ndarray, q: float, b_r: float, b_a: float,
            u: float, alpha: float, beta: float) -> None:
    """Filter j's update of this tick stands: posterior, prior, biases, q (clamped),
    control, and the smoothed and windowed q."""
    qc = q if q < Q_MAX else Q_MAX
    for i in range(4):
        st[j, S_XPOST + i] = fv[F_SCR + i]
        st[j, S_XPRIOR + i] = fv[F_SCR + 4 + i]
    st[j, S_BR] = b_r
    st[j, S_BA] = b_a
    st[j, S_Q] = qc
    st[j, S_U] = u
    st[j, S_QS] += alpha * (qc - st[j, S_QS])
    st[j, S_QW] += beta * (qc - st[j, S_QW])


@nb.njit(cache=True, nogil=True, inline="always")
def _blend_weights(st: np.ndarray, fv: np.ndarray, iv: np.ndarray, nact: int,
                   blend: int) -> tuple[int, int, float, float]:
    """Firing weights (fuzzy statistic through the tabulated App. A curve) and the
    blending weights of the contributing filters, normalised.  Returns (flags, best
    model or -1, sum of the raw weights, smallest per-tick q)."""
    flags = 0
    G = iv[I_G]
    og = iv[I_QGRID]
    oc = iv[I_WCURVE]
    relative = iv[I_FSTAT] == FSTAT_RELATIVE
    best = -1
    qmin = np.inf           # smallest per-tick q (the monitor's statistic)
    smin = np.inf           # smallest fuzzy statistic (the best model)
    for a in range(nact):
        j = iv[IV_ACT + a]
        if st[j, S_CONTRIB] != 0.0:
            qj = st[j, S_Q]
            if qj < qmin:
                qmin = qj
            sj = st[j, S_QW] if relative else qj
            if sj < smin:
                smin = sj
                best = j
    total = 0.0
    for a in range(nact):
        j = iv[IV_ACT + a]
        if st[j, S_CONTRIB] != 0.0:
            if relative:        # relative to the best model, scaled to a matched filter's mean
                sj = st[j, S_QW]
                x = MEAS_DIM * sj / smin if smin > 0.0 else (0.0 if sj <= 0.0 else Q_MAX)
            else:
                x = st[j, S_Q]
            f = firing_weight(x, fv, og, oc, G)
            st[j, S_F] = f
            if blend == _BAYES:
                w = st[j, S_P]
            elif blend == _LQG:
                w = 1.0
            else:
                w = f
            st[j, S_W] = w
            total += w
        else:
            st[j, S_F] = 0.0
            st[j, S_W] = 0.0
    if total > 0.0:
        for a in range(nact):
            j = iv[IV_ACT + a]
            st[j, S_W] = st[j, S_W] / total
    elif best >= 0:          # there are contributing models but none fired
        flags |= _NO_RULE_FIRED
        if iv[I_FALLBACK] == FALLBACK_BEST:
            st[best, S_W] = 1.0
    return flags, best, total, qmin


@nb.njit(cache=True, nogil=True, inline="always")
def _blend_estimates(mat: np.ndarray, st: np.ndarray, fv: np.ndarray, iv: np.ndarray,
                     nact: int, best: int, total: float) -> tuple[float, float]:
    """The blended force reference and, where any model has weight, the blended state,
    next prior, deviations from the equilibria and biases (kept for bumpless starts).
    Returns (force reference [N], sum of the weights used)."""
    out = 0.0
    for i in range(16):
        fv[F_SCR + i] = 0.0
    wsum = 0.0
    bias_r = 0.0
    bias_a = 0.0
    for a in range(nact):
        j = iv[IV_ACT + a]
        w = st[j, S_W]
        if w == 0.0 and best == j and total == 0.0:
            w = 1.0                        # passive fallback: the estimate is still the best
        if w != 0.0:
            out += st[j, S_W] * st[j, S_U]
            wsum += w
            bias_r += w * st[j, S_BR]
            bias_a += w * st[j, S_BA]
            for i in range(4):
                xb = mat[j, i, M_XBAR]
                fv[F_SCR + i] += w * st[j, S_XPOST + i]
                fv[F_SCR + 4 + i] += w * st[j, S_XPRIOR + i]
                fv[F_SCR + 8 + i] += w * (st[j, S_XPOST + i] - xb)
                fv[F_SCR + 12 + i] += w * (st[j, S_XPRIOR + i] - xb)
    if wsum > 0.0:
        for i in range(4):
            fv[F_XHAT + i] = fv[F_SCR + i]
            fv[F_XHATM + i] = fv[F_SCR + 4 + i]
            fv[F_XDEV + i] = fv[F_SCR + 8 + i]
            fv[F_XDEVM + i] = fv[F_SCR + 12 + i]
        fv[F_BIAS] = bias_r
        fv[F_BIAS + 1] = bias_a
    return out, wsum


@nb.njit(cache=True, nogil=True, inline="always")
def _restart_nonfinite(mat: np.ndarray, st: np.ndarray, fv: np.ndarray, iv: np.ndarray,
                       nact: int, wsum: float) -> None:
    """Restart the filters whose update went non-finite at their equilibrium (plus the
    blended deviation and biases when there is a blend)."""
    for a in range(nact):
        j = iv[IV_ACT + a]
        if st[j, S_BAD] != 0.0:
            for i in range(4):
                x = mat[j, i, M_XBAR]
                if wsum > 0.0:
                    x += fv[F_XDEVM + i]
                st[j, S_XPRIOR + i] = x
                st[j, S_XPOST + i] = x
            st[j, S_BR] = fv[F_BIAS] if wsum > 0.0 else 0.0
            st[j, S_BA] = fv[F_BIAS + 1] if wsum > 0.0 else 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def _human_filter(fv: np.ndarray, xf0: float, xf1: float, accel_mps2: float) -> int:
    """Advance the human-body filter on the measured acceleration; a non-finite state is
    reset to rest (returns the NONFINITE_STATE flag then, else 0)."""
    n0 = fv[F_HAD] * xf0 + fv[F_HAD + 1] * xf1 + fv[F_HBD] * accel_mps2
    n1 = fv[F_HAD + 2] * xf0 + fv[F_HAD + 3] * xf1 + fv[F_HBD + 1] * accel_mps2
    if math.isfinite(n0) and math.isfinite(n1):
        fv[F_XF] = n0
        fv[F_XF + 1] = n1
        return 0
    fv[F_XF] = 0.0
    fv[F_XF + 1] = 0.0
    return _NONFINITE_STATE


@nb.njit(cache=True, nogil=True, inline="always")
def preview_clamp(fv: np.ndarray, iv: np.ndarray, out: float) -> float:
    """The stop clamp on the force reference ``out`` [N] (> 0 extends, i.e. pushes away
    from the compression stop): clipped to the bounds :func:`_clamp_check` left in
    ``fv[F_PVC_FMIN]`` / ``fv[F_PVC_FMAX]`` (0 when they cross), a change counted in
    ``iv[I_PVCLAMP_TICKS]``."""
    lo = fv[F_PVC_FMIN]
    hi = fv[F_PVC_FMAX]
    clipped = min(max(out, lo), hi) if lo <= hi else 0.0
    if clipped != out:
        iv[I_PVCLAMP_TICKS] += 1
    return clipped


@nb.njit(_SIG_STEP, cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]
def bank_step(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
              fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, rattlespace_m: float,
              accel_mps2: float, force_meas_n: float) -> float:
    """One tick of the bank (see the module docstring).  Allocation-free (compiled without
    the numba runtime), never raises."""
    clamp_on = iv[I_PVCLAMP]        # the stop clamp's bounds, for this step only
    iv[I_PVCLAMP] = 0
    iv[I_PVCHECKED] = 0
    if not (math.isfinite(rattlespace_m) and math.isfinite(accel_mps2)
            and math.isfinite(force_meas_n)):
        iv[I_FLAGS] = _NONFINITE_INPUT
        return 0.0
    flags = 0
    blend = iv[I_BLEND]
    sentinel = iv[I_SENTINEL] if blend == _MOVING and iv[I_MODE] == MODE_AIR else -1
    u_in, y0, y1 = _measurements(fv, rattlespace_m, accel_mps2, force_meas_n)
    # contacts are rare while the stop-contact window (last tick's) is within its budget
    mass_estimate(fv, u_in, rattlespace_m, accel_mps2, fv[F_SC_TIME] < fv[F_SC_BUDGET])
    wheel_hop_track(fv, rattlespace_m, force_meas_n)
    mass_schedule(st, active, fv, iv, nbr, vec, mat, fv[F_MES + ME_EST], fv[F_MES + ME_KEST],
                  fv[F_MES + ME_CEST], fv[F_WHS + WHS_HZ], blend)
    xf0 = fv[F_XF]
    xf1 = fv[F_XF + 1]
    alpha = fv[F_ALPHA]
    beta = fv[F_QW_ALPHA]
    nact = iv[I_NACT]
    nd = iv[I_DELAY]
    layer = iv[I_LAYER]
    if math.isnan(fv[F_FFW]):           # first reading since reset: rate filter at rest
        fv[F_FFW] = -fv[F_FFB] * rattlespace_m
    comfort = travel_comfort_share(fv, rattlespace_m)
    # ---- the running filters
    e_min = np.inf          # unusable test: min over models of the innovation / sensor range
    for a in range(nact):
        j = iv[IV_ACT + a]
        st[j, S_CONTRIB] = 0.0
        st[j, S_BAD] = 0.0
        q, r0, r1, b_r, b_a, u = _filter_update(j, mat, vec, st, fv, nd, u_in, y0, y1,
                                                force_meas_n, xf0, xf1, comfort)
        if math.isnan(q):
            st[j, S_BAD] = 1.0
            st[j, S_Q] = Q_MAX
            st[j, S_U] = 0.0
            flags |= _NONFINITE_STATE
            continue
        _accept(j, st, fv, q, b_r, b_a, u, alpha, beta)
        if j != sentinel and (vec[j, V_LAYER] < 0.0 or vec[j, V_LAYER] == layer):
            st[j, S_CONTRIB] = 1.0          # (a warming layer's filters only run)
            e = max(abs(r0) * fv[F_UNUSE_R], abs(r1) * fv[F_UNUSE_A])
            if e < e_min:
                e_min = e
    # ---- blending
    bayes_update(st, S_P, S_Q, S_CONTRIB, vec, V_LLC, fv[F_PFLOOR], iv, IV_ACT, nact)
    wflags, best, total, qmin = _blend_weights(st, fv, iv, nact, blend)
    flags |= wflags
    out, wsum = _blend_estimates(mat, st, fv, iv, nact, best, total)
    air = iv[I_AIR]
    fv[F_PVC_AIRW] = st[air, S_W] if air >= 0 else 0.0
    if flags & _NONFINITE_STATE:
        _restart_nonfinite(mat, st, fv, iv, nact, wsum)
    # ---- estimator monitor (docs/design.md §9), human-body filter, guard, spool model
    flags |= _monitor(fv, iv, qmin, e_min)
    flags |= stop_contact(fv, iv, rattlespace_m)
    flags |= ride_height(fv, iv, rattlespace_m)
    flags |= _human_filter(fv, xf0, xf1, accel_mps2)
    out = stop_guard(fv, iv, out * (fv[F_AUTH] * fv[F_SC_AUTH]), rattlespace_m)
    out = stop_barrier(fv, iv, out, rattlespace_m)
    if clamp_on != 0:
        out = preview_clamp(fv, iv, out)
    if not math.isfinite(out):
        out = 0.0
        flags |= _NONFINITE_STATE
    servo_update(fv, nd, out, force_meas_n, rattlespace_m)
    if blend == _MOVING:
        tire_load_update(fv, iv, rattlespace_m, accel_mps2)
        supervise(st, active, fv, iv, nbr, vec, mat)
    iv[I_NUPD] = nact
    iv[I_TICK] += 1
    iv[I_FLAGS] = flags
    fv[F_OUT] = out
    return out


@nb.njit(_SIG_TICK, cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]
def bank_tick(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
              fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, rattlespace_m: float,
              accel_mps2: float, force_meas_n: float, run_st: np.ndarray,
              run_active: np.ndarray, run_models: np.ndarray) -> float:
    """:func:`bank_step`, then the running layer's rows copied into ``run_st`` /
    ``run_active`` / ``run_models`` (:func:`gather_running_layer`; nothing to copy for
    0-row arrays, a one-layer bank's).  Allocation-free, never raises."""
    u = bank_step(mat, vec, st, active, fv, iv, nbr, rattlespace_m, accel_mps2, force_meas_n)
    if run_st.shape[0] > 0:
        gather_running_layer(st, active, iv, run_st, run_active, run_models)
    return u


@nb.njit(cache=True, nogil=True, inline="always")
def raise_travel_envelope(fv: np.ndarray) -> None:
    """Call the travel law (:meth:`BankRuntime.call_travel_law`): raise the travel
    schedule's usage envelope so that the next step finds it at the running schedule's
    full-travel usage at least.  No effect when the schedule is off."""
    if fv[F_TS_ON] == 0.0:
        return
    full = fv[F_TS + 1] + 1.0 / fv[F_TS + 2]
    decay = fv[F_TS + 3]
    target = full / decay if decay > 0.0 else full     # the step decays it once first
    if not fv[F_TS_ENV] >= target:
        fv[F_TS_ENV] = target


@nb.njit(cache=True, nogil=True, inline="always")
def _clamp_check(fv: np.ndarray, iv: np.ndarray, rows: np.ndarray, ticks: np.ndarray,
                 impulse: np.ndarray, brake_rows: np.ndarray, clamp_m: float,
                 clamp_points: int, reading_m: float, road_velocity: np.ndarray,
                 start: int) -> None:
    """The stop clamp's prediction (``design.preview_stop_clamp_m``): the force bounds of
    :func:`controller.road_preview.clamp_force_bounds_n` over the first ``clamp_points``
    look-ahead ticks, up to ``fv[F_PVC_BRAKE]`` of braking times the estimator monitor's
    authority (a degraded estimate brakes no more than it drives), in ``fv[F_PVC_FMIN]`` /
    ``fv[F_PVC_FMAX]`` for the next step and ``iv[I_PVCLAMP]`` 1; 0 (no clamp) while
    the prediction is not trusted or the clamp is off.

    Trusted: the running mean of the squared error of the prediction at the last of
    those ticks, against the reading that came (``F_PVC_MS``, the predictions kept in a
    ring by the tick they are for), is below ``F_PVC_TRUST2``.  A bank on a layer far
    from its plant (before its estimator has moved it) drifts by metres there and is
    not trusted; on its plant the error is that of the law's own force, a few mm.  Nor
    while the airborne model has more than :data:`CLAMP_AIRBORNE_WEIGHT` of the blend
    (a wheel that may be leaving the road: the deviation from the on-ground equilibria
    then carries the airborne model's, and the on-ground prediction runs to metres)."""
    iv[I_PVCHECKED] = 1
    if clamp_points <= 0:
        iv[I_PVCLAMP] = 0
        return
    layer = iv[I_LAYER]
    if layer >= rows.shape[0]:
        iv[I_PVCLAMP] = 0
        return
    centre = fv[F_TS]
    tick = iv[I_TICK]
    slot = tick % PVC_RING
    if fv[F_PVC_FOR + slot] == tick:    # the prediction made for this tick: its error
        e = reading_m - centre - fv[F_PVC_PRED + slot]
        e2 = e * e
        if not e2 < 1.0:                # NaN or a metre off: as a metre
            e2 = 1.0
        fv[F_PVC_MS] += fv[F_PVC_ALPHA] * (e2 - fv[F_PVC_MS])
    f_min, f_max, last = clamp_force_bounds_n(rows, ticks, impulse, brake_rows, layer,
                                              fv[F_XDEV:F_XDEV + 4], reading_m, centre,
                                              road_velocity, start, clamp_points, clamp_m,
                                              fv[F_PVC_BRAKE] * fv[F_AUTH])
    ahead = tick + ticks[min(clamp_points, ticks.shape[0]) - 1]
    slot = ahead % PVC_RING
    fv[F_PVC_PRED + slot] = last
    fv[F_PVC_FOR + slot] = ahead
    if not (fv[F_PVC_MS] < fv[F_PVC_TRUST2] and fv[F_PVC_AIRW] <= CLAMP_AIRBORNE_WEIGHT):
        iv[I_PVCLAMP] = 0
        return
    fv[F_PVC_FMIN] = f_min
    fv[F_PVC_FMAX] = f_max
    iv[I_PVCLAMP] = 1


@nb.njit(cache=True, nogil=True, inline="always")
def _preview_check(fv: np.ndarray, iv: np.ndarray, rows: np.ndarray, ticks: np.ndarray,
                   impulse: np.ndarray, force_rows: np.ndarray, brake_rows: np.ndarray,
                   trigger_m: np.ndarray, edge_trigger_m: float, trusted_from_tick: int,
                   clamp_m: float, clamp_points: int, reading_m: float, force_meas_n: float,
                   road_velocity: np.ndarray, start: int) -> bool:
    """:meth:`BankRuntime.check_road_preview` on the packed state: the stop clamp's
    prediction for the next step (:func:`_clamp_check`, every law); then predict the
    reading by the running layer's model and call the travel law when the peak passes
    the layer's trigger (before ``trusted_from_tick``: the edge's prediction, no force,
    and trigger) or is not finite.  A layer the predictor does not have calls it too."""
    _clamp_check(fv, iv, rows, ticks, impulse, brake_rows, clamp_m, clamp_points,
                 reading_m, road_velocity, start)
    if fv[F_TS_ON] == 0.0:          # a fixed weight set: no travel law to call
        return False
    layer = iv[I_LAYER]
    if layer >= rows.shape[0] or layer >= trigger_m.shape[0]:
        raise_travel_envelope(fv)
        return True
    if iv[I_TICK] < trusted_from_tick:
        force_meas_n = 0.0
        trigger = edge_trigger_m
    else:
        trigger = trigger_m[layer]
    peak = predicted_peak_m(rows, ticks, impulse, force_rows, layer, fv[F_XDEV:F_XDEV + 4],
                            force_meas_n, reading_m, fv[F_TS], road_velocity, start)
    if peak <= trigger:
        return False
    raise_travel_envelope(fv)
    return True


@nb.njit(cache=True, nogil=True)
def road_preview_check(fv: np.ndarray, iv: np.ndarray, rows: np.ndarray, ticks: np.ndarray,
                       impulse: np.ndarray, force_rows: np.ndarray, brake_rows: np.ndarray,
                       trigger_m: np.ndarray, edge_trigger_m: float, trusted_from_tick: int,
                       clamp_m: float, clamp_points: int, reading_m: float,
                       force_meas_n: float, road_velocity: np.ndarray, start: int) -> bool:
    """:func:`_preview_check` alone (:meth:`BankRuntime.check_road_preview`)."""
    return _preview_check(fv, iv, rows, ticks, impulse, force_rows, brake_rows, trigger_m,
                          edge_trigger_m, trusted_from_tick, clamp_m, clamp_points,
                          reading_m, force_meas_n, road_velocity, start)


@nb.njit(_SIG_TICK_PREVIEW, cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]
def bank_tick_preview(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
                      fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, rattlespace_m: float,
                      accel_mps2: float, force_meas_n: float, run_st: np.ndarray,
                      run_active: np.ndarray, run_models: np.ndarray, rows: np.ndarray,
                      ticks: np.ndarray, impulse: np.ndarray, force_rows: np.ndarray,
                      brake_rows: np.ndarray, trigger_m: np.ndarray, edge_trigger_m: float,
                      trusted_from_tick: int, clamp_m: float, clamp_points: int,
                      road_velocity: np.ndarray, start: int) -> float:
    """The road preview's check (:func:`_preview_check`: ``iv[I_PVCALL]`` 1 when it
    called the travel law), then :func:`bank_tick`, in one call: what
    :meth:`BankRuntime.check_road_preview` and :meth:`BankRuntime.step` do one after
    the other, to the bit.  Allocation-free, never raises."""
    called = _preview_check(fv, iv, rows, ticks, impulse, force_rows, brake_rows,
                            trigger_m, edge_trigger_m, trusted_from_tick, clamp_m, clamp_points,
                            rattlespace_m, force_meas_n, road_velocity, start)
    iv[I_PVCALL] = 1 if called else 0
    return bank_tick(mat, vec, st, active, fv, iv, nbr, rattlespace_m, accel_mps2,
                     force_meas_n, run_st, run_active, run_models)


@nb.njit(_SIG_TICK_AT_REST, cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]
def bank_tick_at_rest(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
                      fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, rattlespace_m: float,
                      accel_mps2: float, force_meas_n: float, run_st: np.ndarray,
                      run_active: np.ndarray, run_models: np.ndarray, rows: np.ndarray,
                      ticks: np.ndarray, impulse: np.ndarray, brake_rows: np.ndarray,
                      clamp_m: float, clamp_points: int, no_road: np.ndarray,
                      start: int) -> float:
    """The stop clamp's prediction with the road at rest (:func:`_clamp_check` on
    ``no_road[start:]``, no samples: the state's momentum alone;
    ``design.stop_clamp_road_at_rest``), then :func:`bank_tick`: the tick without a live
    road preview (none when a preview's check made it for this tick already:
    :meth:`BankRuntime.check_road_preview` then :meth:`BankRuntime.step`).
    Allocation-free, never raises."""
    if iv[I_PVCHECKED] == 0:
        _clamp_check(fv, iv, rows, ticks, impulse, brake_rows, clamp_m, clamp_points,
                     rattlespace_m, no_road, start)
    return bank_tick(mat, vec, st, active, fv, iv, nbr, rattlespace_m, accel_mps2,
                     force_meas_n, run_st, run_active, run_models)


@nb.njit(nogil=True)          # compiled on first use only (bench and tests)
def bank_steps(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
               fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, data: np.ndarray) -> float:
    """:func:`bank_step` over the rows of ``data`` (N x 3: rattlespace [m], load-cell
    force [N], sprung acceleration [m/s^2]) in one compiled loop; the sum of the blended
    forces [N] (so the work cannot be optimised away)."""
    acc = 0.0
    for k in range(data.shape[0]):
        acc += bank_step(mat, vec, st, active, fv, iv, nbr, data[k, 0], data[k, 1], data[k, 2])
    return acc


@nb.njit(_SIG_CFG, cache=True, nogil=True)
def bank_configure(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
                   fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, blend: int) -> None:
    """Switch the blending mode: set the running filters (new ones start bumpless)."""
    J = st.shape[0]
    iv[I_BLEND] = blend
    iv[I_MODE] = MODE_GROUND
    iv[I_SENTINEL] = -1
    single = iv[I_SINGLE]
    if blend == _LQG:
        for j in range(J):
            if active[j] and j != single:
                deactivate(j, st, active, iv)
        if not active[single]:
            activate(single, st, active, fv, iv, mat, QS_INIT, 1.0)
    elif blend == _MOVING:
        centre = -1
        qbest = np.inf
        for j in range(J):
            if active[j] and vec[j, V_AIR] == 0.0 and st[j, S_QS] < qbest:
                qbest = st[j, S_QS]
                centre = j
        if centre < 0:
            centre = single
        enter_moving(st, active, fv, iv, nbr, vec, mat, centre)
    else:                   # the running layer's models and the airborne model
        n_run = 0
        for j in range(J):
            if vec[j, V_LAYER] < 0.0 or vec[j, V_LAYER] == iv[I_LAYER]:
                n_run += 1
        for j in range(J):
            if vec[j, V_LAYER] < 0.0 or vec[j, V_LAYER] == iv[I_LAYER]:
                if not active[j]:
                    activate(j, st, active, fv, iv, mat, QS_INIT, 1.0 / n_run)
            elif active[j]:
                deactivate(j, st, active, iv)
    for j in range(J):              # a warming layer starts over
        if active[j] and vec[j, V_LAYER] >= 0.0 and vec[j, V_LAYER] != iv[I_LAYER]:
            deactivate(j, st, active, iv)
    iv[I_LCAND] = -1
    iv[I_LSINCE] = 0
    total = 0.0
    for j in range(J):
        if active[j]:
            total += st[j, S_P]
    for j in range(J):
        if active[j]:
            st[j, S_P] = st[j, S_P] / total if total > 0.0 else 1.0


@nb.njit(_SIG_CFG, cache=True, nogil=True)
def bank_reset(mat: np.ndarray, vec: np.ndarray, st: np.ndarray, active: np.ndarray,
               fv: np.ndarray, iv: np.ndarray, nbr: np.ndarray, blend: int) -> None:
    """Initial state: every filter at its equilibrium, p uniform, history cleared."""
    J = st.shape[0]
    iv[I_NACT] = 0
    for j in range(J):
        active[j] = False
        for c in range(st.shape[1]):
            st[j, c] = 0.0
        st[j, S_QS] = QS_INIT
        st[j, S_QW] = QS_INIT
    fv[F_XF] = 0.0
    fv[F_XF + 1] = 0.0
    fv[F_XV] = 0.0
    fv[F_FFW] = np.nan
    fv[F_BIAS] = 0.0
    fv[F_BIAS + 1] = 0.0
    fv[F_STOP] = 0.0
    fv[F_GUARD_S] = 1.0
    fv[F_SB_DF] = 0.0
    fv[F_SB_V] = np.nan
    fv[F_MON_SUM] = 0.0
    fv[F_AUTH] = 1.0
    fv[F_SC_TIME] = 0.0
    fv[F_SC_AUTH] = 1.0
    fv[F_RH] = 0.0
    fv[F_AMEAN] = 0.0
    fv[F_TS_ENV] = 0.0
    fv[F_TS_BETA] = 0.0
    mass_estimate_reset(fv)
    wheel_hop_reset(fv)
    for i in range(MAX_DELAY):
        fv[F_PEND + i] = 0.0
    for i in range(4):
        fv[F_XHAT + i] = fv[F_XINIT + i]
        fv[F_XHATM + i] = fv[F_XINIT + i]
        fv[F_XDEV + i] = 0.0
        fv[F_XDEVM + i] = 0.0
    fv[F_THRESH] = fv[F_TFLOOR]
    fv[F_SIGNAL] = 0.0
    fv[F_LOAD] = 1.0
    fv[F_GOFF] = 0.0
    fv[F_GON] = 0.0
    fv[F_HINC] = 1.0
    fv[F_HTOT] = 0.0
    fv[F_OUT] = 0.0
    for b in range(iv[I_NB] + 2 * (2 * iv[I_LD] + 1)):   # histogram and tire-load rings
        fv[iv[I_HIST] + b] = 0.0
    for b in range(iv[I_MON_N]):                         # monitor window
        fv[iv[I_MON_RING] + b] = 0.0
    for idx in (I_MODE, I_SINCE_SWITCH, I_SINCE_RECENTRE, I_PROBE_PTR, I_PROBE_CNT,
                I_FLAGS, I_NUPD, I_NSWITCH, I_NLEARN, I_NRECENTRE, I_TICK, I_NLIFT_LOAD,
                I_LPTR, I_LCNT, I_MON_PTR, I_MON_DEG, I_MON_OK, I_MON_BAD,
                I_MON_NDEG, I_MON_DEGTICKS, I_SB_TICKS, I_GUARD_TICKS, I_GUARD_LEAD_TICKS,
                I_SC_DEG, I_SC_OK, I_SC_TICKS,
                I_SC_EPISODES, I_SC_NDEG, I_SC_DEGTICKS, I_RH_OFF):
        iv[idx] = 0
    iv[I_SC_QUIET] = iv[I_SC_GAP]      # no contact yet: the first contact tick opens an episode
    iv[I_MON_CNT] = -iv[I_MON_N]
    iv[I_SENTINEL] = -1
    iv[I_LAYER] = iv[I_LAYER0]
    iv[I_SINGLE] = iv[I_SINGLE0]
    iv[I_LSINCE] = 0
    iv[I_LCAND] = -1
    iv[I_NLAYERSW] = 0
    iv[I_PVCALL] = 0
    iv[I_PVCLAMP] = 0
    iv[I_PVCHECKED] = 0
    iv[I_PVCLAMP_TICKS] = 0
    fv[F_PVC_MS] = 4.0 * fv[F_PVC_TRUST2]     # not trusted until predictions come true
    for i in range(PVC_RING):
        fv[F_PVC_FOR + i] = -1.0
    iv[I_CENTRE] = iv[I_SINGLE]
    bank_configure(mat, vec, st, active, fv, iv, nbr, blend)
    n = 0
    for j in range(J):
        if active[j]:
            n += 1
    for j in range(J):
        for i in range(4):
            st[j, S_XPRIOR + i] = mat[j, i, M_XBAR]
            st[j, S_XPOST + i] = mat[j, i, M_XBAR]
        st[j, S_P] = 1.0 / n if active[j] else 0.0
        st[j, S_QS] = QS_INIT
        st[j, S_QW] = QS_INIT
        st[j, S_BR] = 0.0
        st[j, S_BA] = 0.0


@nb.njit(cache=True, nogil=True)
def _select(dst_mat: np.ndarray, dst_vec: np.ndarray, all_mat: np.ndarray,
            all_vec: np.ndarray, s: int, w: int) -> None:
    """Copy the packed tables of noise entry s and weight set w into place (no allocation)."""
    dst_mat[:, :, :] = all_mat[s, w]
    dst_vec[:, :] = all_vec[s, w]


# ============================================================================ Python side


def config_of(design: Design) -> RigConfig:
    """The configuration recorded in the artifact (``metadata['config_toml']``)."""
    text = design.metadata.get("config_toml") if isinstance(design.metadata, dict) else None
    if not text:
        return default_config()
    return _parsed_config(str(text))


@functools.lru_cache(maxsize=16)
def _parsed_config(text: str) -> RigConfig:
    """The configuration of a TOML text, remembered: a runtime's build reads its
    design's configuration several times (7 ms a parse); RigConfig is immutable."""
    return parse_config(tomllib.loads(text))


def _vehicle_mkc(cfg: RigConfig) -> FloatArray:
    """The configured sprung mass [kg], spring rate [N/m] and damping [N s/m]."""
    v = cfg.vehicle
    return np.array([v.sprung_mass_kg, v.suspension_stiffness_n_per_m,
                     v.suspension_damping_ns_per_m])


def _layers(design: Design, cfg: RigConfig) -> tuple[FloatArray, NDArray[np.int64], int]:
    """(layers (L, 3): sprung mass [kg], spring rate [N/m], damping [N s/m]; layer of each
    model, -1 airborne; on-ground models per layer) of the design, whose layers are those
    its own configuration names (``config_of(design)``, the vehicle of ``cfg``)."""
    layers = np.array(layer_params(config_of(design), cfg.vehicle), dtype=float)
    return layer_table(design.equilibrium, design.airborne, layers, cfg.vehicle.gravity_mps2)


def _layer_tires(design: Design) -> FloatArray:
    """Tire stiffness scale of each layer of the design (its own configuration's
    ``design.tire_stiffness_scales``, :func:`controller.config.layer_tire_scales`)."""
    return np.array(layer_tire_scales(config_of(design)), dtype=float)


def _layer_wheel_hops(design: Design, cfg: RigConfig) -> FloatArray:
    """The passive wheel-hop frequency [Hz] each layer's rig reads
    (:func:`controller.wheel_hop.passive_wheel_hop_hz` of :func:`layer_config` of ``cfg``
    with the layer's scales, the design's own configuration's :func:`layer_grid`), where
    the bank has tire layers; 1 elsewhere (the layer distance does not use it then)."""
    grid = layer_grid(config_of(design))
    if len({t for *_mkc, t in grid}) < 2:
        return np.ones(len(grid))
    return np.array([passive_wheel_hop_hz(layer_config(cfg, *scales)) for scales in grid])


#: tire stiffness scales about the configured tire the wheel hop's sensitivity is taken on
_TIRE_SPAN = (0.85, 1.15)


def _tire_weight(cfg: RigConfig) -> float:
    """1 / (d log wheel hop / d log tire stiffness) of the configured rig: the tire
    layers' distance in units of log tire stiffness (about 1 / 0.25)."""
    lo, hi = (passive_wheel_hop_hz(layer_config(cfg, 1.0, tire_scale=t)) for t in _TIRE_SPAN)
    return math.log(_TIRE_SPAN[1] / _TIRE_SPAN[0]) / math.log(hi / lo)


def _nominal_layer(layers: FloatArray, tires: FloatArray, cfg: RigConfig) -> int:
    """The layer nearest the configured vehicle and tire (the bank's layer after a
    reset)."""
    if not (np.all(layers > 0.0) and np.all(tires > 0.0)):
        return 0
    return int(np.argmin(np.sum(np.abs(np.log(layers / _vehicle_mkc(cfg))), axis=1)
                         + np.abs(np.log(tires))))


def default_single_model(design: Design, cfg: RigConfig) -> int:
    """The on-ground model of the sprung-mass layer nearest the configured mass whose
    linearisation deflection is nearest the static tire deflection (ties: damping scale
    nearest 1)."""
    x2s = static_tire_deflection_m(cfg)
    defl = cfg.design.linearisation_deflections_m
    scales = cfg.design.tire_damping_scales
    layers, layer, _ = _layers(design, cfg)
    home = _nominal_layer(layers, _layer_tires(design), cfg)
    best, key_best = -1, (math.inf, math.inf)
    for j in range(design.n_models):
        if design.airborne[j] or layer[j] != home:
            continue
        di, si = int(design.grid_index[j, 0]), int(design.grid_index[j, 1])
        key = (abs(defl[di] - x2s), abs(scales[si] - 1.0))
        if key < key_best:
            best, key_best = j, key
    if best < 0:
        raise ValueError("the design has no on-ground model")
    return best


def _pack(design: Design, cfg: RigConfig) -> tuple[FloatArray, FloatArray]:
    """Packed per-model tables for every (noise entry, weight set): (S, W, J, 4, MAT_COLS)
    and (S, W, J, VEC_COLS)."""
    layers, layer, _ = _layers(design, cfg)
    # each model reads the rattlespace about its own static position, M_l g / K_l: the LVDT
    # reads 0 at rest (zeroed there, or the ride height set by preload), and the loop adds
    # the configured rig's M g / K (F_STATIC), so model j's filter gets the reading +
    # M_l g / K_l - M g / K (V_YSTAT; one layer: 0, as before).  A spring rate other than
    # the configured one moves the model's own static deflection even where the body sits
    # (preload), as its mass does.
    veh = cfg.vehicle
    lay = layers[np.maximum(layer, 0)]
    ystat = np.where((layer >= 0) & (len(layers) > 1),
                     lay[:, 0] * veh.gravity_mps2 / lay[:, 1] - float(design.static_rattlespace_m),
                     0.0)
    tires = _layer_tires(design)
    hop = _layer_wheel_hops(design, cfg)[np.maximum(layer, 0)]
    log_params = np.where((layer >= 0)[:, None],
                          np.log(np.column_stack([lay, tires[np.maximum(layer, 0)], hop])), 0.0)
    J, S, W = design.n_models, design.n_noise, design.n_weight_sets
    wc = cfg.design.schedule_weight_sets[0] - 1
    mat = np.zeros((S, W, J, 4, MAT_COLS))
    vec = np.zeros((S, W, J, VEC_COLS))
    for s in range(S):
        for w in range(W):
            m = mat[s, w]
            v = vec[s, w]
            m[:, :, M_A:M_A + 4] = design.filter_A[:, s]
            m[:, :, M_BY:M_BY + 2] = design.filter_By[:, s]
            m[:, :, M_BU] = design.filter_Bu[:, s]
            m[:, :, M_B] = design.filter_b[:, s]
            m[:, :, M_L:M_L + 2] = design.kalman_gain[:, s]
            m[:, :, M_CT:M_CT + 2] = np.transpose(design.C_meas, (0, 2, 1))
            m[:, :, M_KX] = design.lq_gain[w, :, :4]
            m[:, 0, M_LB:M_LB + 2] = design.bias_gain[:, s, 0]
            m[:, 1, M_LB:M_LB + 2] = design.bias_gain[:, s, 1]
            v[:, V_D:V_D + 2] = design.D_meas
            v[:, V_FINV:V_FINV + 4] = design.innovation_cov_inv[:, s].reshape(J, 4)
            v[:, V_LOGDET] = design.innovation_logdet[:, s]
            v[:, V_KF:V_KF + 2] = design.lq_gain[w, :, 4:6]
            ka = design.actuator_gain[w]
            v[:, V_KA:V_KA + ka.shape[1]] = ka
            if 0 <= wc < W:             # the travel schedule's comfort gain (§12)
                m[:, :, M_KC] = design.lq_gain[wc, :, :4]
                v[:, V_KFC:V_KFC + 2] = design.lq_gain[wc, :, 4:6]
                kac = design.actuator_gain[wc]
                v[:, V_KAC:V_KAC + kac.shape[1]] = kac
            v[:, V_AIR] = design.airborne.astype(float)
            v[:, V_LLC] = [log_likelihood_constant(float(ld), MEAS_DIM)
                           for ld in design.innovation_logdet[:, s]]
            v[:, V_LAYER] = layer
            v[:, V_LOGP:V_LOGP + 5] = log_params
            v[:, V_YSTAT] = ystat
    return mat, vec


@dataclass(frozen=True)
class _Tables:
    """Where the variable-length tables start in ``fv`` (after the scalar slots)."""

    grid: int           # fuzzy q grid (G entries), then the weight curve (G)
    curve: int
    hist: int           # residual history (HIST_BINS), then the tire-load rings
    monitor_ring: int   # the estimator monitor's window ring
    size: int           # entries of fv
    load_step: int      # Δ of the tire-load estimate [ticks]


def _table_offsets(design: Design, cfg: RigConfig, mon: MonitorSettings) -> _Tables:
    dt = float(design.dt_s)
    G = int(design.fuzzy_q_grid.shape[0])
    load_step = max(1, round(cfg.moving_bank.load_estimate_window_s / dt))
    grid = FV_HEAD
    hist = grid + 2 * G
    ring = hist + HIST_BINS + 2 * (2 * load_step + 1)
    return _Tables(grid, grid + G, hist, ring, ring + mon.window_ticks, load_step)


def _history_ticks(cfg: RigConfig, dt: float) -> float:
    """N of the exponential window of the residual history [ticks]."""
    return max(2.0, cfg.moving_bank.history_window_s / dt)


def _float_parameters(design: Design, cfg: RigConfig, mon: MonitorSettings, t: _Tables,
                      x_init: FloatArray) -> FloatArray:
    """``fv``: the scalar parameters (slots ``F_*``) and the tables, state zeroed."""
    dt = float(design.dt_s)
    mb = cfg.moving_bank
    fv = np.zeros(t.size)
    fv[F_YOFF:F_YOFF + 2] = design.y_offset
    fv[F_HAD:F_HAD + 4] = np.asarray(design.human_filter_Ad).reshape(4)
    fv[F_HBD:F_HBD + 2] = design.human_filter_Bd
    fv[F_STATIC] = design.static_rattlespace_m
    fv[F_SDECAY], fv[F_SKP], fv[F_SFLIM], fv[F_SOLIM] = design.servo_model[:4]
    fv[F_FFC], fv[F_FFA], fv[F_FFSTALL], fv[F_FFFLOOR] = design.servo_model[5:9]
    fv[F_FFB] = fv[F_FFA] / dt
    tau = mb.smoothing_time_s
    fv[F_ALPHA] = 1.0 - math.exp(-dt / tau) if tau > 0.0 else 1.0
    fv[F_PFLOOR] = cfg.bayes.probability_floor
    fv[F_BS_K], fv[F_BS_LO], fv[F_BS_HI] = design.bump_stop
    fv[F_GUARD_W] = cfg.design.stop_guard_m
    fv[F_GUARD_LEAD] = cfg.design.stop_guard_lead_s
    fv[F_GUARD_V0] = cfg.design.stop_guard_lead_deadband_mps
    fv[F_ME:F_ME + ME_SIZE] = mass_estimator_parameters(
        cfg, (float(design.bump_stop[1]), float(design.bump_stop[2])))
    fv[F_WH:F_WH + WH_SIZE] = wheel_hop_tracker_parameters(cfg)
    fv[F_LHYST] = LAYER_HYSTERESIS
    layers = _layers(design, cfg)[0]     # the layer distance counts the axes that vary
    fv[F_LWK] = float(np.unique(layers[:, 1]).size > 1)
    fv[F_LWC] = float(np.unique(layers[:, 2]).size > 1)
    fv[F_LWT] = _tire_weight(cfg) if np.unique(_layer_tires(design)).size > 1 else 0.0
    fv[F_TS:F_TS + SCHEDULE_SIZE] = travel_schedule(cfg).as_array()
    fv[F_PVC_ALPHA] = 1.0 - math.exp(-dt / CLAMP_TRUST_WINDOW_S)
    fv[F_PVC_TRUST2] = cfg.design.preview_clamp_trust_m ** 2
    fv[F_SB:F_SB + BARRIER_SIZE] = stop_barrier_parameters(
        cfg, float(fv[F_FFSTALL]), float(fv[F_SFLIM])).as_array()
    fv[F_PVC_BRAKE] = (braking_force_n(cfg, float(fv[F_FFSTALL]), float(fv[F_SFLIM]))
                       if cfg.design.preview_clamp_brake else 0.0)
    aw = cfg.design.accel_mean_window_s
    fv[F_AMEAN_ALPHA] = 1.0 - math.exp(-dt / aw) if aw > 0.0 else 0.0
    fw = cfg.fuzzy.window_s
    fv[F_QW_ALPHA] = 1.0 - math.exp(-dt / fw) if fw > 0.0 else 1.0
    fv[F_MON_THR] = mon.degrade_sum
    fv[F_MON_REARM] = mon.rearm_sum
    fv[F_AUTH_STEP] = mon.authority_step
    fv[F_UNUSE_R] = 1.0 / mon.rattlespace_bound_m
    fv[F_UNUSE_A] = 1.0 / mon.accel_bound_mps2
    sc = stop_contact_settings(cfg, dt)
    fv[F_SC_DECAY], fv[F_SC_TICK], fv[F_SC_BAND] = sc.decay, sc.tick_s, sc.band_m
    fv[F_SC_BUDGET], fv[F_SC_REARM], fv[F_SC_FLOOR] = sc.budget_s, sc.rearm_level_s, sc.authority
    rh = ride_height_settings(cfg, dt)
    fv[F_RH_ALPHA], fv[F_RH_CENTRE] = rh.alpha, rh.centre_m
    fv[F_RH_WARN], fv[F_RH_CLEAR] = rh.warn_m, rh.clear_m
    fv[F_TFLOOR] = chi2_threshold_floor(mb.threshold_quantile, MEAS_DIM)
    fv[F_LOFF] = mb.liftoff_load_fraction
    fv[F_LON] = mb.liftoff_load_fraction / mb.hysteresis_ratio
    fv[F_LH] = mb.liftoff_load_fraction * max(1, round(mb.liftoff_detection_time_s / dt))
    veh = cfg.vehicle
    if veh.gravity_mps2 > 0.0:          # else no static load: the estimate stays 1
        fv[F_LINVG] = 1.0 / veh.gravity_mps2
        fv[F_LC] = veh.unsprung_mass_kg / (
            (veh.sprung_mass_kg + veh.unsprung_mass_kg) * veh.gravity_mps2
            * (t.load_step * dt) ** 2)
    fv[F_QUANT] = mb.threshold_quantile
    fv[F_FORGET] = 1.0 / (1.0 - 1.0 / _history_ticks(cfg, dt))
    fv[F_RECENTRE] = RECENTRE_RATIO
    fv[F_HLO] = HIST_LO_LOG10
    fv[F_HWIDTH] = (HIST_HI_LOG10 - HIST_LO_LOG10) / HIST_BINS
    fv[F_XINIT:F_XINIT + 4] = x_init
    fv[t.grid:t.curve] = design.fuzzy_q_grid
    fv[t.curve:t.hist] = design.fuzzy_weight_curve
    return fv


def _int_parameters(design: Design, cfg: RigConfig, mon: MonitorSettings, t: _Tables,
                    single_model: int, k: int) -> NDArray[np.int64]:
    """``iv``: the integer parameters (slots ``I_*``), state zeroed."""
    dt = float(design.dt_s)
    mb = cfg.moving_bank
    J = design.n_models
    air = np.flatnonzero(design.airborne)
    n_ground = J - int(air.size)
    iv = np.zeros(IV_HEAD + J, dtype=np.int64)
    iv[I_J] = J
    iv[I_G] = t.curve - t.grid
    iv[I_SINGLE] = single_model
    iv[I_AIR] = int(air[0]) if air.size else -1
    iv[I_NG] = n_ground
    iv[I_K] = k
    iv[I_DWELL] = max(1, round(mb.dwell_time_s / dt))
    iv[I_PROBE] = max(1, round(mb.probe_period_s / dt))
    iv[I_FSTAT] = FSTAT_RELATIVE if cfg.fuzzy.statistic == "relative" else FSTAT_RAW
    iv[I_MON_N] = mon.window_ticks
    iv[I_MON_RING] = t.monitor_ring
    iv[I_MON_RECOVER] = mon.rearm_ticks
    iv[I_MON_MAXBAD] = mon.window_ticks
    sc = stop_contact_settings(cfg, dt)
    iv[I_SC_ON] = int(sc.degrade)
    iv[I_SC_RECOVER] = sc.rearm_ticks
    iv[I_SC_GAP] = sc.episode_gap_ticks
    iv[I_FALLBACK] = (FALLBACK_BEST if cfg.fuzzy.no_fire_fallback == "best_model"
                      else FALLBACK_PASSIVE)
    iv[I_QGRID] = t.grid
    iv[I_WCURVE] = t.curve
    iv[I_HIST] = t.hist
    iv[I_NB] = HIST_BINS
    iv[I_MINLEARN] = max(1, int(_history_ticks(cfg, dt) // 4))
    iv[I_RECOMP] = HIST_RECOMPUTE_TICKS
    layers, layer, n_tire = _layers(design, cfg)
    iv[I_NPROBE] = max(0, min(n_tire - k, MAX_PROBE_CANDIDATES))   # within the layer
    iv[I_NLAYER] = len(layers)
    iv[I_NTIRE] = n_tire
    iv[I_SINGLE0] = single_model
    iv[I_LAYER0] = max(int(layer[single_model]), 0)
    iv[I_LDWELL] = max(1, round(LAYER_DWELL_S / dt))
    iv[I_DELAY] = design.compute_delay_ticks
    iv[I_LD] = t.load_step
    return iv


class RunningModels:
    """The models of the layer the bank runs, as the tick record carries them
    (docs/recording.md): ``models`` (W,) the bank's index of each column; ``q``,
    ``firing_weight``, ``probability``, ``u_model``, ``active`` (W,) and ``x_post`` (W, 4)
    are the :class:`BankRuntime` read-outs of the same names for those models.  A
    one-layer bank's are views of the read-outs (W = J, every model, nothing copied); a
    layered bank's (docs/design.md §11) hold the running layer's on-ground models and the
    shared airborne model (W = J / L for L layers, about), refreshed by every step, so a
    record is as wide for the default bank's 190 models as for a one-layer bank's 4."""

    __slots__ = ("active", "firing_weight", "models", "probability", "q", "u_model",
                 "x_post")

    def __init__(self, st: np.ndarray, active: np.ndarray, models: NDArray[np.int64]
                 ) -> None:
        self.models = models
        self.q = st[:, S_Q]
        self.firing_weight = st[:, S_W]
        self.probability = st[:, S_P]
        self.u_model = st[:, S_U]
        self.active = active
        self.x_post = st[:, S_XPOST:S_XPOST + 4]


class BankRuntime:
    """The controller bank at run time (API in docs/architecture.md "Runtime step").

    ``step()`` is one numba call on preallocated buffers; the kernels are compiled (or
    loaded from numba's cache) at import and exercised once in ``__init__``.

    Public (J,) views, updated in place by every step: ``q`` (likelihood quotients,
    clamped to Q_MAX), ``firing_weight`` (the normalised blending weights actually used:
    fuzzy firing weights, or the probabilities in BAYES mode; sum 1 unless nothing
    fired), ``raw_firing_weight`` (the App. A curve at q, before normalisation),
    ``probability`` (MMAE p_j, kept in every mode), ``u_model`` (each model's LQ force),
    ``q_smoothed``, ``active`` (the filters that ran).  ``x_post`` (J, 4), ``x_prior``
    (J, 4), ``xf`` (2,), ``x_blend`` (4,), absolute states (positions from the unloaded
    springs); ``x_deviation`` (4,), the blended deviation of the models' estimates from
    their own equilibria.  Inactive filters read 0 in q/weights/forces.  ``running``
    (:class:`RunningModels`): the same read-outs for the models of the layer the bank
    runs, which the loop records (for a one-layer bank, views of the above).
    """

    def __init__(self, design: Design, blending: Blending | int = Blending.FUZZY,
                 weight_set: int = 1, single_model: int | None = None, *,
                 cfg: RigConfig | None = None) -> None:
        design.validate()
        self.design = design
        self.cfg = cfg if cfg is not None else config_of(design)
        cfg_ = self.cfg
        J = design.n_models
        self.n_models = J
        dt = float(design.dt_s)
        fallback = cfg_.fuzzy.no_fire_fallback
        prob_floor = cfg_.bayes.probability_floor
        if not prob_floor < 1.0 / J:
            raise ValueError(f"bayes.probability_floor {prob_floor!r}: must be below "
                             f"1/J = {1.0 / J:g} for this bank of {J} models")
        if single_model is None:
            single_model = default_single_model(design, cfg_)
        if not (0 <= int(single_model) < J) or bool(design.airborne[int(single_model)]):
            raise ValueError(f"single_model {single_model!r}: must be an on-ground model "
                             f"index in [0, {J})")
        self.single_model = int(single_model)
        self._all_mat, self._all_vec = _pack(design, cfg_)
        layers, layer, n_tire = _layers(design, cfg_)
        #: (L, 3) sprung mass [kg], spring rate [N/m] and damping [N s/m] of the bank's
        #: layers (docs/design.md §11)
        self.layer_params = layers
        #: sprung masses of the bank's layers [kg]
        self.layer_masses_kg = np.ascontiguousarray(layers[:, 0])
        self._nbr = neighbour_table(design.grid_index, design.airborne, layer)
        k = min(int(cfg_.moving_bank.active_models), n_tire)
        x_init = np.asarray(design.equilibrium[self.single_model], dtype=float)
        mon = monitor_settings(cfg_, dt, MEAS_DIM)
        self.monitor = mon
        self.stop_contact_settings: StopContactSettings = stop_contact_settings(cfg_, dt)
        if design.compute_delay_ticks > MAX_DELAY:
            raise ValueError(f"design compute delay {design.compute_delay_ticks} ticks: the "
                             f"runtime supports at most {MAX_DELAY}")
        layout = _table_offsets(design, cfg_, mon)
        fv = _float_parameters(design, cfg_, mon, layout, x_init)
        iv = _int_parameters(design, cfg_, mon, layout, self.single_model, k)
        self.no_fire_fallback = fallback
        self.prob_floor = float(prob_floor)
        self.active_models_k = k

        self._fv = fv
        self._iv = iv
        self._mat = np.zeros((J, 4, MAT_COLS))
        self._vec = np.zeros((J, VEC_COLS))
        self._st = np.zeros((J, ST_COLS))
        self._active = np.zeros(J, dtype=np.bool_)
        # reset state of each filter: its equilibrium (the airborne one: the nominal state)
        xbar = np.where(np.isfinite(design.equilibrium), design.equilibrium, x_init[None, :])
        self._all_mat[:, :, :, :, M_XBAR] = xbar[None, None, :, :]
        self.noise_index = design.noise_index(0, 0)
        self.weight_set = 1
        self._table_w = 0               # the packed table of the selected weight set
        # the schedule's parameters on each of its thresholds, one row per name of
        # THRESHOLDS: the reading's, a live road preview's (use_preview_schedule
        # switches between the two) and the travel governor's of the comfort set run
        # alone (preview live or not)
        self._schedules = np.stack([travel_schedule(cfg_, t).as_array() for t in THRESHOLDS])
        self.preview_schedule = False
        self.governed = False           # the comfort set runs under the travel governor
        #: ticks after a reset before the road preview trusts the running layer (its
        #: inner trigger and force, controller/road_preview.py): until then the layer is
        #: the configured plant's, not yet an estimate; the sprung-mass estimator
        #: settles, fills one window, and the layer scheduler dwells (docs/design.md §12)
        self.preview_trust_ticks = int(fv[F_ME + ME_SETTLE]) + round(
            (cfg_.design.mass_estimator_window_s + LAYER_DWELL_S) / dt)
        self.blending = Blending(int(blending))
        self.set_road(cfg_.noise.nominal_speed_mps, cfg_.noise.nominal_roughness_gd)
        self.set_weight_set(weight_set)

        self._bind_views()
        rows = running_layer_rows(J, len(layers), n_tire, 0)
        # the step copies the running layer into these (0 rows: a one-layer bank, whose
        # running models are every model, read through views)
        w = rows.size if len(layers) > 1 else 0
        self._st_run = np.zeros((w, ST_COLS))
        self._active_run = np.zeros(w, dtype=np.bool_)
        self._models_run = rows[:w].copy()
        self._gather = w > 0
        #: the running layer's models (the tick record's columns)
        self.running = (RunningModels(self._st_run, self._active_run, self._models_run) if w
                        else RunningModels(self._st, self._active, rows))
        # the step's compiled functions without numba's per-call dispatch
        # (controller/runtime/compiled.py): these arrays are the runtime's own, checked
        # here, and never replaced; the preview's are checked when they change
        own = (self._mat, self._vec, self._st, self._active, self._fv, self._iv, self._nbr,
               0.0, 0.0, 0.0)
        self._step_call: Callable[..., float] = direct_call(bank_step, own)
        run = (self._st_run, self._active_run, self._models_run)
        self._tick_call: Callable[..., float] = direct_call(bank_tick, (*own, *run))
        self._tick_preview_call: Callable[..., float] = bank_tick_preview
        self._preview_bound: tuple[RoadPreview, np.ndarray] | None = None
        # the stop clamp without a live preview: the road at rest
        # (design.stop_clamp_road_at_rest; the preview's predictor, no road velocity;
        # the window's start makes it 21 arguments: a call of exactly 20 left 200 B on
        # the Python heap per tick, up to ~400 kB, until gc.collect() (tracemalloc,
        # tests/test_bank.py::test_no_allocation_per_tick); 21 leave nothing)
        self._no_road = np.zeros(0)
        pv = cached_road_preview(cfg_) if cfg_.design.stop_clamp_road_at_rest else None
        self._at_rest = pv if pv is not None and pv.clamp_points > 0 else None
        self._at_rest_call: Callable[..., float] = bank_tick_at_rest
        if self._at_rest is not None:
            a = self._at_rest
            self._at_rest_args = (a.rows, a.ticks, a.impulse, a.brake_rows, a.clamp_m,
                                  a.clamp_points, self._no_road, 0)
            self._at_rest_call = direct_call(bank_tick_at_rest,
                                             (*own, *run, *self._at_rest_args))
        self._warm_up()
        self.reset()

    def _bind_views(self) -> None:
        """The public read-outs: views into the packed state, updated in place by step."""
        st = self._st
        self.q = st[:, S_Q]
        self.firing_weight = st[:, S_W]
        self.raw_firing_weight = st[:, S_F]
        self.probability = st[:, S_P]
        self.u_model = st[:, S_U]
        self.q_smoothed = st[:, S_QS]
        self.active = self._active
        self.x_post = st[:, S_XPOST:S_XPOST + 4]
        self.x_prior = st[:, S_XPRIOR:S_XPRIOR + 4]
        self.xf = self._fv[F_XF:F_XF + 2]
        self.x_blend = self._fv[F_XHAT:F_XHAT + 4]
        self.x_deviation = self._fv[F_XDEV:F_XDEV + 4]

    # ------------------------------------------------------------------ control
    def _warm_up(self) -> None:
        """Run every code path once on scratch copies so that no compile or first-call
        cost lands in a real tick."""
        for b in Blending:
            st, act = self._st.copy(), self._active.copy()
            fv, iv = self._fv.copy(), self._iv.copy()
            bank_reset(self._mat, self._vec, st, act, fv, iv, self._nbr, int(b))
            for _ in range(3):
                bank_step(self._mat, self._vec, st, act, fv, iv, self._nbr, 0.0, 0.0, 0.0)
            bank_tick(self._mat, self._vec, st, act, fv, iv, self._nbr, math.nan, 0.0, 0.0,
                      self._st_run.copy(), self._active_run.copy(), self._models_run.copy())
            bank_tick_preview(self._mat, self._vec, st, act, fv, iv, self._nbr, 0.0, 0.0, 0.0,
                              self._st_run.copy(), self._active_run.copy(),
                              self._models_run.copy(), np.zeros((1, 1, 4)),
                              np.ones(1, dtype=np.int64), np.zeros((1, 1)), np.zeros((1, 1)),
                              np.zeros((1, 1)), np.zeros(1), 0.0, 0, 0.08, 1, np.zeros(1), 0)
            bank_tick_at_rest(self._mat, self._vec, st, act, fv, iv, self._nbr, 0.0, 0.0, 0.0,
                              self._st_run.copy(), self._active_run.copy(),
                              self._models_run.copy(), np.zeros((1, 1, 4)),
                              np.ones(1, dtype=np.int64), np.zeros((1, 1)),
                              np.zeros((1, 1)), 0.08, 1, self._no_road, 0)
        _select(self._mat, self._vec, self._all_mat, self._all_vec, self.noise_index,
                self._table_w)

    def reset(self) -> None:
        """Initial state: filters at equilibrium, p uniform, human filter at rest."""
        bank_reset(self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                   self._nbr, int(self.blending))
        if self._gather:
            gather_running_layer(self._st, self._active, self._iv, self._st_run,
                                 self._active_run, self._models_run)

    def set_blending(self, blending: Blending | int) -> None:
        """Switch the blending mode (newly running filters start from the blended estimate)."""
        b = Blending(int(blending))
        self.blending = b
        bank_configure(self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                       self._nbr, int(b))

    def set_weight_set(self, weight_set: int) -> None:
        """Select the LQ weight set (1-based, as ``design.weight_set``); 0 = the travel
        schedule between the two sets of ``design.schedule_weight_sets`` (§12).  The
        schedule's comfort set selected alone runs under the travel governor with
        ``design.govern_comfort_set`` (:attr:`governed`): the schedule's machinery on the
        governor's thresholds, the comfort law untouched until near the stops or a
        predicted excursion (§12)."""
        w = int(weight_set)
        n = self.design.n_weight_sets
        comfort, travel = self.cfg.design.schedule_weight_sets
        schedule_ok = 1 <= comfort <= n and 1 <= travel <= n
        governed = self.cfg.design.governs(w) and schedule_ok
        if w == 0:
            if not schedule_ok:
                raise ValueError(f"weight_set 0 (travel schedule): design.schedule_weight_sets "
                                 f"{[comfort, travel]} not within the design's 1..{n}")
            table = travel - 1
        elif governed:
            table = travel - 1          # the travel law's slot; the comfort law's is set w
        elif 1 <= w <= n:
            table = w - 1
        else:
            raise ValueError(f"weight_set {weight_set!r}: allowed 0..{n} (0 = travel schedule)")
        self.weight_set = w
        self.governed = governed
        # the road preview trusts the running layer from this tick after a reset on;
        # never under the travel governor (check_road_preview)
        self._trusted_from_tick = _NEVER_TRUSTED if governed else self.preview_trust_ticks
        self._table_w = table
        self._fv[F_TS_ON] = 1.0 if w == 0 or governed else 0.0
        self.use_preview_schedule(self.preview_schedule)
        _select(self._mat, self._vec, self._all_mat, self._all_vec, self.noise_index, table)

    def set_road(self, speed_mps: float, roughness_gd: float) -> int:
        """Use the noise-table entry nearest (speed, Gd(n0)); returns its flat index."""
        s = nearest_noise_entry(self.design.noise_speeds_mps, self.design.noise_roughness_gd,
                                float(speed_mps), float(roughness_gd))
        self.noise_index = s
        _select(self._mat, self._vec, self._all_mat, self._all_vec, s, self._table_w)
        return s

    # ------------------------------------------------------------------ the tick
    def step(self, rattlespace_m: float, accel_mps2: float, force_meas_n: float) -> float:
        """One controller tick: the actuator force reference [N].  With
        ``design.stop_clamp_road_at_rest`` (and a predictor: ``preview_horizon_s`` > 0) the
        stop clamp first predicts with the road at rest, unless :meth:`check_road_preview`
        ran for this tick.  Never raises."""
        # Python floats take the entry point, any other input the dispatcher (which
        # converts other numbers and refuses the rest: controller/runtime/compiled.py)
        exact = (type(rattlespace_m) is float and type(accel_mps2) is float
                 and type(force_meas_n) is float)
        try:
            if self._at_rest is not None:   # the stop clamp with the road at rest
                return (self._at_rest_call if exact else bank_tick_at_rest)(
                    self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                    self._nbr, rattlespace_m, accel_mps2, force_meas_n, self._st_run,
                    self._active_run, self._models_run, *self._at_rest_args)
            if self._gather:    # a layered bank: the step copies the running layer too
                return (self._tick_call if exact else bank_tick)(
                    self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                    self._nbr, rattlespace_m, accel_mps2, force_meas_n, self._st_run,
                    self._active_run, self._models_run)
            return (self._step_call if exact else bank_step)(
                self._mat, self._vec, self._st, self._active, self._fv, self._iv, self._nbr,
                rattlespace_m, accel_mps2, force_meas_n)
        except (TypeError, ValueError, OverflowError):
            self._iv[I_FLAGS] = _NONFINITE_INPUT
            return 0.0

    @property
    def takes_road_preview(self) -> bool:
        """The law in use takes the road preview (:meth:`check_road_preview` may call
        the travel law): the travel schedule or the governed comfort set."""
        return bool(self._fv[F_TS_ON] != 0.0)

    def use_preview_schedule(self, live: bool) -> None:
        """Road preview (controller/road_preview.py): run the travel schedule on the
        thresholds for a live preview (``design.preview_schedule_*``, ``live``) or on the
        reading-only ones (``design.schedule_start_m`` / ``schedule_full_m``); the
        governed comfort set (:attr:`governed`) keeps the governor's
        (``design.governor_*``) either way.  The usage envelope carries over.  Allocates
        nothing."""
        self.preview_schedule = bool(live)
        which = "governor" if self.governed else "preview" if live else "reading"
        self._fv[F_TS:F_TS + SCHEDULE_SIZE] = self._schedules[THRESHOLDS.index(which)]

    def check_road_preview(self, preview: RoadPreview, reading_m: float, force_meas_n: float,
                           road_velocity: np.ndarray, start: int) -> bool:
        """Road preview (controller/road_preview.py), before :meth:`step`: predict the
        LVDT reading over the preview's horizon by the running layer's model from this
        estimate, the reading ``reading_m``, the load-cell force ``force_meas_n`` [N]
        (``preview.force_rows``) and the road velocity ahead
        ``road_velocity[start:]`` [m/s] (this tick's first), and call the travel law
        (:meth:`call_travel_law`) when the predicted peak passes the running layer's
        ``preview.trigger_m`` or is not finite; the governed comfort set (:attr:`governed`),
        and any law in the first :attr:`preview_trust_ticks` after a reset, predicts
        without the force and takes ``preview.edge_trigger_m``.  For every law, also the
        stop clamp of the next :meth:`step` on the previewed road (``preview.clamp_m``:
        the force bounds that keep the prediction over ``preview.clamp_points``
        look-ahead ticks inside it, :func:`_clamp_check`; a change counted in
        ``counters()["preview_clamp_ticks"]``), which that step then does not redo with
        the road at rest.
        True when it called.  Allocates nothing.  :meth:`step_previewed` does this and
        :meth:`step` in one call."""
        return bool(road_preview_check(
            self._fv, self._iv, preview.rows, preview.ticks, preview.impulse,
            preview.force_rows, preview.brake_rows, preview.trigger_m, preview.edge_trigger_m,
            self._trusted_from_tick, preview.clamp_m, preview.clamp_points, reading_m,
            force_meas_n, road_velocity, start))

    def step_previewed(self, preview: RoadPreview, rattlespace_m: float, accel_mps2: float,
                       force_meas_n: float, road_velocity: np.ndarray, start: int) -> float:
        """:meth:`check_road_preview` (on the reading ``rattlespace_m``) then
        :meth:`step`, to the bit, in one compiled call (the loop's tick with a live
        preview: one call costs a tick less than two); :attr:`preview_called` says
        whether the check called the travel law.  ``preview``'s arrays are C-contiguous
        (as :func:`controller.road_preview.road_preview` builds them), ``road_velocity``
        a C-contiguous float64 array.  Never raises."""
        bound = self._preview_bound
        if bound is None or bound[0] is not preview or bound[1] is not road_velocity:
            self._bind_preview(preview, road_velocity)
        exact = (type(rattlespace_m) is float and type(accel_mps2) is float
                 and type(force_meas_n) is float and type(start) is int)
        try:
            return (self._tick_preview_call if exact else bank_tick_preview)(
                self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                self._nbr, rattlespace_m, accel_mps2, force_meas_n, self._st_run,
                self._active_run, self._models_run, preview.rows, preview.ticks,
                preview.impulse, preview.force_rows, preview.brake_rows, preview.trigger_m,
                preview.edge_trigger_m, self._trusted_from_tick, preview.clamp_m,
                preview.clamp_points, road_velocity, start)
        except (TypeError, ValueError, OverflowError):
            self._iv[I_PVCALL] = 0
            self._iv[I_FLAGS] = _NONFINITE_INPUT
            return 0.0

    def _bind_preview(self, preview: RoadPreview, road_velocity: np.ndarray) -> None:
        """:meth:`step_previewed` on a preview or a road-velocity array it has not
        seen: the compiled step without numba's dispatch when their arrays are of the
        signature's types (checked once here, kept while they are the same objects),
        else through the dispatcher (which refuses them: a flagged tick)."""
        args = (self._mat, self._vec, self._st, self._active, self._fv, self._iv,
                self._nbr, 0.0, 0.0, 0.0, self._st_run, self._active_run, self._models_run,
                preview.rows, preview.ticks, preview.impulse, preview.force_rows,
                preview.brake_rows, preview.trigger_m, preview.edge_trigger_m,
                self._trusted_from_tick, preview.clamp_m, preview.clamp_points, road_velocity, 0)
        self._tick_preview_call = direct_call(bank_tick_preview, args)
        self._preview_bound = (preview, road_velocity)

    @property
    def preview_called(self) -> bool:
        """The last :meth:`step_previewed` called the travel law."""
        return bool(self._iv[I_PVCALL])

    def preview_trust(self, preview: RoadPreview) -> str:
        """How far :meth:`check_road_preview` trusts its prediction on this tick:
        ``"inside"`` (the running layer lies inside the grid: the force and the inner
        trigger, ``preview.trigger_m`` above ``edge_trigger_m``), ``"edge"`` (the running
        layer takes the edge's trigger: on the grid's edge, or every layer without an
        inner trigger), ``"settling"`` (within
        :attr:`preview_trust_ticks` of a reset), ``"governor"`` (the governed comfort
        set), ``"unused"`` (a fixed weight set takes no preview)."""
        if self._fv[F_TS_ON] == 0.0:
            return "unused"
        if self.governed:
            return "governor"
        if self._iv[I_TICK] < self.preview_trust_ticks:
            return "settling"
        inside = preview.trigger_m[int(self._iv[I_LAYER])] != preview.edge_trigger_m
        return "inside" if inside else "edge"

    def call_travel_law(self) -> None:
        """Road preview (controller/road_preview.py): raise the travel schedule's usage
        envelope so that the next step finds it at the running schedule's full-travel
        usage (``design.preview_schedule_full_m`` under :meth:`use_preview_schedule`) at least:
        the travel law has the whole force, then the schedule's usual release follows.
        No effect when the schedule is off (a fixed weight set).  Allocates nothing."""
        raise_travel_envelope(self._fv)

    # ------------------------------------------------------------------ read-outs
    @property
    def flags(self) -> StepFlag:
        return StepFlag(self.flag_bits)

    @property
    def flag_bits(self) -> int:
        """:attr:`flags` as a plain int, for a caller that reads them every tick (an
        enum member costs the loop half a microsecond)."""
        return int(self._iv[I_FLAGS])

    filter_updates = SlotValue(
        "_iv", I_NUPD, int,
        "Kalman filter updates done in the last tick (the work done).")

    @property
    def airborne_mode(self) -> bool:
        """Moving bank: the airborne set is running."""
        return bool(self._iv[I_MODE] == MODE_AIR)

    centre = SlotValue("_iv", I_CENTRE, int, "Moving bank: centre of the running subset.")
    preview_clamp_ticks = SlotValue(
        "_iv", I_PVCLAMP_TICKS, int,
        "Ticks since reset in which the road preview's stop clamp clipped the force toward "
        "a stop (design.preview_stop_clamp_m; counters()['preview_clamp_ticks']).")

    residual_threshold = SlotValue(
        "_fv", F_THRESH, float,
        "The learnt switching threshold T on the smoothed likelihood quotient.")

    switching_signal = SlotValue(
        "_fv", F_SIGNAL, float,
        "Moving bank: the smoothed min q of the on-ground set (the sentinel's when airborne).")

    tire_load_estimate = SlotValue(
        "_fv", F_LOAD, float,
        "Moving bank: the estimated tire load as a fraction of the static load (M + m) g "
        "(model-free, controller.runtime.moving_bank.tire_load_update; lags Δ ticks).")

    @property
    def contact_cusums(self) -> tuple[float, float]:
        """Moving bank: (lift-off, touch-down) CUSUM statistics of the tire-contact test;
        a switch needs one to reach ``contact_cusum_threshold``."""
        return float(self._fv[F_GOFF]), float(self._fv[F_GON])

    contact_cusum_threshold = SlotValue("_fv", F_LH, float,
                                        "Decision threshold of the contact CUSUMs.")

    authority = SlotValue(
        "_fv", F_AUTH, float,
        "Force authority in [0, 1]: 1 armed, ramping to 0 while the monitor has the bank "
        "degraded (controller.monitor).")

    degraded = SlotValue(
        "_iv", I_MON_DEG, bool,
        "The estimator monitor has the bank on its conservative law (DEGRADED).")

    @property
    def monitor_statistic(self) -> float:
        """Window sum of the smallest q over the monitor window, divided by the window
        length (a matched filter averages m = 2); 0 until the window is full."""
        n = int(self._iv[I_MON_N])
        if n == 0 or self._iv[I_MON_CNT] < n:       # settling or filling after a reset
            return 0.0
        return float(self._fv[F_MON_SUM]) / n

    stop_contact_s = SlotValue(
        "_fv", F_SC_TIME, float,
        "Stop-contact time in the monitor's exponential window [s] (controller/stop_contact.py).")

    stop_degraded = SlotValue(
        "_iv", I_SC_DEG, bool,
        "The stop-contact monitor has the bank on its travel-conservative law (STOP_DEGRADED).")

    ride_height_m = SlotValue(
        "_fv", F_RH, float,
        "Ride height: the mean LVDT reading about the stops' centre [m], compression "
        "positive (controller/ride_height.py); 0 after a reset.")

    off_centre = SlotValue(
        "_iv", I_RH_OFF, bool,
        "The ride-height monitor finds the body off the stops' centre (RIDE_HEIGHT).")

    stop_authority = SlotValue(
        "_fv", F_SC_AUTH, float,
        "The stop-contact monitor's force authority: 1 armed, ramping to "
        "safety.stop_contact_authority while stop-degraded.")

    bump_stop_force = SlotValue(
        "_fv", F_STOP, float,
        "The bump-stop force of the last tick, from the LVDT reading [N].")

    #: the end-stop guard's factor on the force of the last tick (1: not acting)
    stop_guard = SlotValue("_fv", F_GUARD_S, float, "End-stop guard factor (stop_guard.py).")

    stop_barrier_force = SlotValue(
        "_fv", F_SB_DF, float,
        "Force the end-stop barrier added to the law's in the last tick [N] (0: not "
        "limiting; > 0 away from the compression stop); counters()['stop_barrier_ticks'] "
        "counts the ticks it limited (stop_barrier.py).")

    comfort_share = SlotValue(
        "_fv", F_TS_BETA, float,
        "The travel schedule's comfort share of the last tick's force, beta in [0, 1] "
        "(0: the travel law alone, or the schedule off; controller/travel_schedule.py).")

    schedule_usage_m = SlotValue(
        "_fv", F_TS_ENV, float,
        "The travel schedule's rattlespace usage envelope [m] (controller/travel_schedule.py).")

    mass_layer = SlotValue(
        "_iv", I_LAYER, int,
        "The sprung-mass layer the bank runs (index into layer_masses_kg; "
        "controller/runtime/mass_layers.py).")

    sprung_mass_est_kg = SlotValue(
        "_fv", F_MES + ME_EST, float,
        "The sprung-mass estimate [kg] (controller/mass_estimator.py: band-passed least "
        "squares on the body equation; the configured mass until the rig has moved enough "
        "to tell, held while it is quiet).")
    spring_rate_est_n_per_m = SlotValue(
        "_fv", F_MES + ME_KEST, float,
        "The suspension spring rate the sprung-mass estimator fits beside the mass [N/m] "
        "(the configured K until it updates).")
    damping_est_ns_per_m = SlotValue(
        "_fv", F_MES + ME_CEST, float,
        "The suspension damping the sprung-mass estimator fits beside the mass [N s/m] "
        "(the configured C until it updates).")
    wheel_hop_hz = SlotValue(
        "_fv", F_WHS + WHS_HZ, float,
        "The passive rig's wheel-hop frequency [Hz] (controller/wheel_hop.py: an AR(2) fit "
        "on the band-passed LVDT while the load cell reads no force; NaN until 8 s of "
        "such data, held while armed).")
    tire_stiffness_est = SlotValue(
        "_fv", F_WHS + WHS_SCALE, float,
        "The tire's stiffness against the configured tire [-], from wheel_hop_hz through "
        "the prediction for the configured rig (controller/wheel_hop.py; NaN with it).")

    @property
    def bias_estimate(self) -> tuple[float, float]:
        """Blended measurement-bias estimates (rattlespace [m], acceleration [m/s^2])."""
        return float(self._fv[F_BIAS]), float(self._fv[F_BIAS + 1])

    def counters(self) -> dict[str, int]:
        iv = self._iv
        return {"ticks": int(iv[I_TICK]), "set_switches": int(iv[I_NSWITCH]),
                "recentres": int(iv[I_NRECENTRE]), "history_samples": int(iv[I_NLEARN]),
                "degradations": int(iv[I_MON_NDEG]),
                "degraded_ticks": int(iv[I_MON_DEGTICKS]),
                "unusable_ticks": int(iv[I_MON_BAD]),
                "load_liftoffs": int(iv[I_NLIFT_LOAD]),
                "stop_barrier_ticks": int(iv[I_SB_TICKS]),
                "preview_clamp_ticks": int(iv[I_PVCLAMP_TICKS]),
                "stop_guard_ticks": int(iv[I_GUARD_TICKS]),
                "stop_guard_lead_ticks": int(iv[I_GUARD_LEAD_TICKS]),
                "stop_contact_ticks": int(iv[I_SC_TICKS]),
                "stop_contact_episodes": int(iv[I_SC_EPISODES]),
                "stop_degradations": int(iv[I_SC_NDEG]),
                "stop_degraded_ticks": int(iv[I_SC_DEGTICKS]),
                "mass_estimate_updates": int(self._fv[F_MES + ME_NUPD]),
                "wheel_hop_updates": int(self._fv[F_WHS + WHS_NUPD]),
                "layer_changes": int(iv[I_NLAYERSW])}

    def snapshot(self) -> dict[str, Any]:
        """Copies of the state (for tests and telemetry; allocates)."""
        return {"q": self.q.copy(), "w": self.firing_weight.copy(),
                "p": self.probability.copy(), "u": self.u_model.copy(),
                "active": self.active.copy(), "x_post": self.x_post.copy(),
                "x_prior": self.x_prior.copy(), "xf": self.xf.copy(),
                "flags": self.flags, "out": float(self._fv[F_OUT])}
