"""Shared pieces of the runtime bank kernel: enums, the packed-buffer layout, small helpers.

The per-tick step is one numba call.  A numba call pays ~40 ns per array argument, so
the runtime packs its data into six buffers instead of ~30 named arrays:

``mat`` (J, 4, MAT_COLS) float, per model, for the *selected* noise entry and weight set:
    filter matrices, Kalman gain, measurement matrix, LQ gain, equilibrium and bias-state
    gains (slots ``M_*`` below).
``vec`` (J, VEC_COLS) float, per model: measurement feed-through, innovation covariance
    inverse and log-determinant, gain parts and the log-likelihood constant (``V_*``).
``st`` (J, ST_COLS) float, per-model state (``S_*``; the public (J,) views point into it).
``active`` (J,) bool: the filters that run this tick.
``fv`` float: scalar parameters, then scalar state (incl. the moving bank's tire-contact
    test, F_LOFF..F_LC, the bump-stop input F_BS_*, the estimator monitor F_MON_*, the
    end-stop guard F_GUARD_*, the end-stop barrier F_SB*, the stop-contact monitor F_SC_*,
    the ride-height monitor F_RH*), then
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

from controller.config import MAX_CLAMP_LOOKAHEAD_TICKS, MAX_COMPUTE_DELAY_TICKS
from controller.mass_estimator import (
    ME_APREV,
    ME_BV,
    ME_BZ,
    ME_C,
    ME_CEST,
    ME_EST,
    ME_FPREV,
    ME_HI,
    ME_HOLD,
    ME_HOLD_TICKS,
    ME_HP,
    ME_HPA,
    ME_HPV,
    ME_HPY,
    ME_HPZ,
    ME_INV_DT,
    ME_K,
    ME_KEST,
    ME_LAMBDA,
    ME_LO,
    ME_LP,
    ME_LPA,
    ME_LPV,
    ME_LPY,
    ME_LPZ,
    ME_M0,
    ME_NSEEN,
    ME_NUPD,
    ME_RAV,
    ME_RAZ,
    ME_RVV,
    ME_RZV,
    ME_RZZ,
    ME_SAA,
    ME_SAY,
    ME_SETTLE,
    ME_SIZE,
    ME_SMIN,
    ME_STATE_SIZE,
    ME_STOP_HI,
    ME_STOP_LO,
    ME_WC,
    ME_WK,
    ME_ZPREV,
)
from controller.modes import Blending
from controller.runtime.layout import BufferLayout
from controller.travel_schedule import SCHEDULE_SIZE
from controller.wheel_hop import (
    WH_FDECAY,
    WH_FMAX,
    WH_HI,
    WH_LAMBDA,
    WH_LO,
    WH_NMIN,
    WH_ON,
    WH_RMIN,
    WH_SETTLE,
    WH_SIZE,
    WH_SOS,
    WH_STATE_SIZE,
    WH_STEP,
    WH_TAB_F,
    WH_TAB_S,
    WH_TFIT,
    WHS_B1,
    WHS_B2,
    WHS_BP,
    WHS_COUNT,
    WHS_FENV,
    WHS_HZ,
    WHS_NPASS,
    WHS_NUPD,
    WHS_NWIN,
    WHS_R11,
    WHS_R12,
    WHS_R22,
    WHS_SCALE,
    WHS_Y1,
    WHS_Y2,
    ar2_frequency_hz,
)

__all__ = ["Blending", "StepFlag"]


class StepFlag(IntFlag):
    """Bits of ``BankRuntime.flags`` after a step.

    NONFINITE_* and DIVERGED (the estimate is unusable) are faults.  DEGRADED is not: the
    innovation statistics say the models do not fit, and the bank runs its conservative
    law (force authority ramped to zero) until they recover (docs/design.md §9).
    STOP_DEGRADED is not either: the stop-contact time in its window is above the budget
    and the bank runs its travel-conservative law until it re-arms (§9.8)."""

    NONFINITE_INPUT = 1
    NONFINITE_STATE = 2
    NO_RULE_FIRED = 4
    DIVERGED = 8
    DEGRADED = 16
    STOP_DEGRADED = 32      # the stop-contact monitor has the bank on its travel-conservative law
    STOP_CONTACT = 64       # the tick lies in a bump-stop contact episode (a read-out, no fault)
    RIDE_HEIGHT = 128       # the body's mean position is off the stops' centre (read-out, no fault)


_STOP_DEGRADED = int(StepFlag.STOP_DEGRADED)
_STOP_CONTACT = int(StepFlag.STOP_CONTACT)
_RIDE_HEIGHT = int(StepFlag.RIDE_HEIGHT)

MEAS_DIM = 2            # m, measurement dimension [rattlespace_abs, accel]
Q_MAX = 1.0e12          # likelihood quotients are clamped here (keeps smoothing finite)
QS_INIT = float(MEAS_DIM)   # smoothed q starts at E[q] of a matched filter

PVC_RING = MAX_CLAMP_LOOKAHEAD_TICKS + 1  # the stop clamp's ring of predictions [ticks]
MAX_DELAY = MAX_COMPUTE_DELAY_TICKS  # pending spool commands kept (design.compute_delay_ticks)

# The packed buffers, slot by slot (controller/runtime/layout.py assigns the offsets in
# declaration order; tests/test_buffer_layout.py checks every constant below is a slot).
# --- mat columns (per model, 4 rows)
MAT = BufferLayout("mat")
M_A = MAT.slot(4)  # filter_A
M_BY = MAT.slot(2)  # filter_By
M_BU = MAT.slot()  # filter_Bu
M_B = MAT.slot()  # filter_b
M_L = MAT.slot(2)  # Kalman gain L
M_CT = MAT.slot(2)  # C_meas transposed
M_KX = MAT.slot()  # state part of the LQ gain
M_XBAR = MAT.slot()  # equilibrium x̄_j (airborne model: the nominal static state)
M_LB = MAT.slot(2)  # rows 0 / 1: bias-state gains (rattlespace / acceleration bias)
M_KC = MAT.slot()  # state part of the travel schedule's comfort LQ gain
MAT_COLS = MAT.size
# --- vec columns (per model)
VEC = BufferLayout("vec")
V_D = VEC.slot(2)  # D_meas
V_FINV = VEC.slot(4)  # F^-1, row major
V_LOGDET = VEC.slot()  # log|F|
V_KF = VEC.slot(2)  # human-filter part of the LQ gain
V_AIR = VEC.slot()  # 1.0 for an airborne model, else 0.0
V_LLC = VEC.slot()  # log-likelihood constant -(m/2) log 2π - ½ log|F|
V_KA = VEC.slot(3 + MAX_DELAY)  # actuator part of the gain (spool, force, w, pending)
V_LAYER = VEC.slot()  # sprung-mass layer of the model (-1: airborne)
V_YSTAT = VEC.slot()  # own static deflection less the rig's: M_l g / K_l - M g / K [m]
V_LOGP = VEC.slot(5)  # log of the layer's [M, K, C, tire scale, passive wheel hop] (mass_layers.py)
V_KFC = VEC.slot(2)  # travel schedule's comfort gain: human-filter part
V_KAC = VEC.slot(3 + MAX_DELAY)  # travel schedule's comfort gain: actuator part
VEC_COLS = VEC.size
# --- st columns
ST = BufferLayout("st")
S_XPRIOR = ST.slot(4)  # prior state estimate
S_XPOST = ST.slot(4)  # posterior state estimate
S_Q = ST.slot()
S_W = ST.slot()
S_P = ST.slot()
S_U = ST.slot()
S_QS = ST.slot()
S_F = ST.slot()
S_CONTRIB = ST.slot()
S_BAD = ST.slot()
S_BR = ST.slot()  # measurement-bias estimate: rattlespace [m]
S_BA = ST.slot()  # measurement-bias estimate: acceleration [m/s^2]
S_QW = ST.slot()  # windowed q (exponential window fuzzy.window_s): fuzzy statistic
ST_COLS = ST.size

# --- fv: scalar parameters
FV = BufferLayout("fv")
F_YOFF = FV.slot(2)  # y_offset
F_HAD = FV.slot(4)  # human filter Ad, row major
F_HBD = FV.slot(2)  # human filter Bd
F_STATIC = FV.slot()  # static rattlespace M g / K [m]
F_ALPHA = FV.slot()  # smoothing factor of q (1 - exp(-dt / tau))
F_PFLOOR = FV.slot()  # Bayesian probability floor
F_TFLOOR = FV.slot()  # lowest residual threshold (chi-square quantile)
F_QUANT = FV.slot()  # threshold quantile
F_FORGET = FV.slot()  # 1 / (1 - 1/N) growth of the history increment (exponential window)
F_RECENTRE = FV.slot()  # re-centre when qs[best] < ratio * qs[centre]
F_HLO = FV.slot()  # histogram lower edge, log10 q
F_HWIDTH = FV.slot()  # histogram bin width, decades
# --- fv: scalar state
F_XF = FV.slot(2)  # human-filter states
F_XHAT = FV.slot(4)  # blended posterior (absolute) state estimate
F_XHATM = FV.slot(4)  # blended next prior
F_XINIT = FV.slot(4)  # nominal static state (reset fallback)
F_THRESH = FV.slot()  # learnt residual threshold
F_SIGNAL = FV.slot()  # smoothed min q of the on-ground set (moving bank)
F_HINC = FV.slot()  # current history increment
F_HTOT = FV.slot()  # total history weight
F_OUT = FV.slot()  # last force reference [N]
F_SCR = FV.slot(16)  # scratch
F_XDEV = FV.slot(4)  # blended posterior deviation from the models' equilibria
F_XDEVM = FV.slot(4)  # blended next-prior deviation (bumpless starts)
# --- fv: spool model of the force path (controller/actuator.py)
F_SDECAY = FV.slot()  # e^{-T/tau}
F_SKP = FV.slot()  # PI proportional gain [1/N]
F_SFLIM = FV.slot()  # force reference limit [N]
F_SOLIM = FV.slot()  # spool command limit
F_XV = FV.slot()  # spool position estimate
F_PEND = FV.slot(MAX_DELAY)  # spool commands not yet at the valve, newest first
# --- fv: flow feedforward of the force loop (controller/actuator.py FlowFeedforward)
F_FFC = FV.slot()  # c, spool per m/s of extension rate at zero load (0 = off)
F_FFA = FV.slot()  # a, coefficient of the low-pass on the differentiated LVDT
F_FFB = FV.slot()  # b = a / T [1/s]
F_FFSTALL = FV.slot()  # stall force A Ps [N]
F_FFFLOOR = FV.slot()  # floor of the relative valve pressure drop
F_FFW = FV.slot()  # w, state of the rate filter [m/s]; NaN = no reading since reset
# --- fv: tire-contact test of the moving bank (controller/runtime/moving_bank.py)
F_LOFF = FV.slot()  # lift-off CUSUM reference: estimated tire load / static load
F_LON = FV.slot()  # touch-down CUSUM reference (F_LOFF / hysteresis ratio)
F_LH = FV.slot()  # decision threshold of both CUSUMs [load fraction x ticks]
F_LOAD = FV.slot()  # estimated tire load / static load (controller/runtime/moving_bank.py)
F_GOFF = FV.slot()  # lift-off CUSUM statistic
F_GON = FV.slot()  # touch-down CUSUM statistic
F_LINVG = FV.slot()  # 1 / g
F_LC = FV.slot()  # m / ((M + m) g (Δ T)^2): weight of the rattlespace second difference
# --- fv: bump stops as a known filter input (LVDT frame)
F_BS_K = FV.slot()  # stop stiffness [N/m] (0: no stop input)
F_BS_LO = FV.slot()  # LVDT reading where the rebound (extension) stop engages [m]
F_BS_HI = FV.slot()  # LVDT reading where the compression stop engages [m]
F_BIAS = FV.slot(2)  # blended bias estimates (bumpless starts)
F_QW_ALPHA = FV.slot()  # smoothing factor of the fuzzy statistic (1 - exp(-dt / window))
# --- fv: estimator monitor (docs/design.md §9)
F_MON_THR = FV.slot()  # degrade when the window sum of min q exceeds this
F_MON_REARM = FV.slot()  # re-arm when it stays below this for I_MON_RECOVER ticks
F_MON_SUM = FV.slot()  # window sum of min q (state)
F_AUTH = FV.slot()  # force authority in [0, 1] (state)
F_AUTH_STEP = FV.slot()  # authority change per tick (1 / ramp ticks)
F_UNUSE_R = FV.slot()  # unusable: every model's |rattlespace innovation| above this [m]
F_UNUSE_A = FV.slot()  # ... or every model's |acceleration innovation| above this [m/s^2]
F_STOP = FV.slot()  # bump-stop force of the last tick [N] (read-out)
F_AMEAN = FV.slot()  # running mean of the accelerometer reading (its bias) [m/s^2] (state)
F_AMEAN_ALPHA = FV.slot()  # weight of the running mean, 1 - exp(-dt / accel_mean_window_s) (0 off)
F_GUARD_W = FV.slot()  # end-stop guard: zone width in front of each stop [m] (0: off)
F_GUARD_S = FV.slot()  # end-stop guard: factor applied to the force of the last tick (read-out)
F_GUARD_LEAD = FV.slot()  # end-stop guard: lead on the approach rate [s] (0: the distance law)
F_GUARD_V0 = FV.slot()  # end-stop guard: deadband of the approach rate [m/s]
F_SB = FV.slot(9)  # end-stop barrier: StopBarrier.as_array() (stop_barrier.py; M = 0: off)
F_SB_DF = FV.slot()  # end-stop barrier: force added in the last tick [N] (read-out)
F_SB_V = FV.slot()  # end-stop barrier: low-passed LVDT rate [m/s] (state; NaN after reset)
# --- fv: stop-contact monitor (controller/stop_contact.py, docs/design.md §9.8)
F_SC_DECAY = FV.slot()  # λ of the exponential window, per tick
F_SC_TICK = FV.slot()  # contact time one contact tick adds [s]
F_SC_BAND = FV.slot()  # contact band in front of each stop [m]
F_SC_BUDGET = FV.slot()  # degrade when the window's contact time exceeds this [s]
F_SC_REARM = FV.slot()  # re-arm when it stays below this for I_SC_RECOVER ticks [s]
F_SC_FLOOR = FV.slot()  # force authority of the travel-conservative law
F_SC_TIME = FV.slot()  # contact time in the window [s] (state)
F_SC_AUTH = FV.slot()  # the monitor's force authority in [F_SC_FLOOR, 1] (state)
# --- fv: ride-height monitor (controller/ride_height.py, docs/design.md §9.9)
F_RH_ALPHA = FV.slot()  # α, weight of a new reading per tick
F_RH_CENTRE = FV.slot()  # LVDT reading half-way between the stops [m]
F_RH_WARN = FV.slot()  # off centre above this |ride height| [m] (0: never)
F_RH_CLEAR = FV.slot()  # centred again below this |ride height| [m]
F_RH = FV.slot()  # ride height: mean LVDT reading about the stops' centre [m] (state; 0: reset)
F_LHYST = FV.slot()  # layer hysteresis: switch when distance(new) + this < distance(current)
F_LWK = FV.slot()  # 1: the layers differ in spring rate (the layer distance counts K), else 0
F_LWC = FV.slot()  # 1: the layers differ in damping (the layer distance counts C), else 0
F_LWT = FV.slot()  # layers differ in tire stiffness: 1 / d log(wheel hop) / d log(tire), else 0
F_ME = FV.slot(ME_SIZE)  # sprung-mass estimator: mass_estimator_parameters() (λ = 0: off)
F_MES = FV.slot(ME_STATE_SIZE)  # sprung-mass estimator: state (controller/mass_estimator.py)
F_TS_ON = FV.slot()  # travel schedule on (weight set 0, or the governed comfort set; §12)
F_TS = FV.slot(SCHEDULE_SIZE)  # travel schedule: TravelSchedule.as_array() (travel_schedule.py)
F_TS_ENV = FV.slot()  # travel schedule: usage envelope [m] (state)
F_TS_BETA = FV.slot()  # travel schedule: the comfort law's share of the last tick (read-out)
F_WH = FV.slot(WH_SIZE)  # wheel-hop tracker: wheel_hop_tracker_parameters() (WH_ON = 0: off)
F_WHS = FV.slot(WH_STATE_SIZE)  # wheel-hop tracker: state (controller/wheel_hop.py)
# --- fv: the road preview's stop clamp (controller/road_preview.py, docs/design.md §12)
F_PVC_ALPHA = FV.slot()  # weight of a new squared prediction error per tick
F_PVC_TRUST2 = FV.slot()  # the clamp acts while F_PVC_MS is below this [m^2]
F_PVC_MS = FV.slot()  # mean-square error of the clamp's last look-ahead prediction [m^2] (state)
F_PVC_AIRW = FV.slot()  # the airborne model's weight in the last step's blend (read-out)
F_PVC_PRED = FV.slot(PVC_RING)  # prediction of the reading for tick t, at t % PVC_RING (state)
F_PVC_FOR = FV.slot(PVC_RING)  # the tick that slot predicts (state; -1: none)
F_PVC_BRAKE = FV.slot()  # the clamp's largest braking force [N] (design.preview_clamp_brake)
F_PVC_FMIN = FV.slot()  # the clamp's least force for the next step [N] (state)
F_PVC_FMAX = FV.slot()  # the clamp's greatest force for the next step [N] (state)
FV_HEAD = FV.size  # the fuzzy table starts here

# --- iv: parameters
IV = BufferLayout("iv")
I_J = IV.slot()
I_G = IV.slot()
I_BLEND = IV.slot()
I_SINGLE = IV.slot()
I_AIR = IV.slot()
I_NG = IV.slot()
I_K = IV.slot()
I_DWELL = IV.slot()
I_PROBE = IV.slot()
I_MON_MAXBAD = IV.slot()  # ticks of unusable estimate that set DIVERGED (the monitor window)
I_FALLBACK = IV.slot()
I_QGRID = IV.slot()
I_WCURVE = IV.slot()
I_HIST = IV.slot()
I_NB = IV.slot()
I_MINLEARN = IV.slot()
I_RECOMP = IV.slot()
I_NPROBE = IV.slot()
I_DELAY = IV.slot()  # D, compute delay of the design [ticks]
I_LD = IV.slot()  # Δ, difference step of the tire-load estimate [ticks]
# --- iv: state
I_MODE = IV.slot()  # 0 on ground, 1 airborne (moving bank)
I_CENTRE = IV.slot()  # centre of the moving subset
I_SENTINEL = IV.slot()  # on-ground filter kept running (zero weight) while airborne
I_SINCE_SWITCH = IV.slot()
I_SINCE_RECENTRE = IV.slot()
I_PROBE_PTR = IV.slot()
I_PROBE_CNT = IV.slot()
I_FLAGS = IV.slot()
I_NUPD = IV.slot()  # filter updates in the last tick
I_NSWITCH = IV.slot()  # set switches since reset
I_NLEARN = IV.slot()  # history samples learnt
I_NRECENTRE = IV.slot()  # re-centres since reset
I_TICK = IV.slot()
I_NACT = IV.slot()  # number of running filters
I_NLIFT_LOAD = IV.slot()  # lift-offs declared by the tire-load CUSUM since reset
I_LPTR = IV.slot()  # next write position in the tire-load rings
I_LCNT = IV.slot()  # samples in the tire-load rings (saturates at 2Δ+1)
# --- iv: fuzzy statistic and estimator monitor
I_FSTAT = IV.slot()  # fuzzy input: FSTAT_RAW (per-tick q, App. A) or FSTAT_RELATIVE
I_MON_N = IV.slot()  # monitor window length N [ticks] (0: monitor off)
I_MON_RING = IV.slot()  # offset of the monitor's window ring in fv
I_MON_RECOVER = IV.slot()  # ticks below the re-arm level needed to re-arm
I_MON_PTR = IV.slot()  # next write position in the window ring (state)
I_MON_CNT = IV.slot()  # samples in the window (saturates at N) (state)
I_MON_DEG = IV.slot()  # 1 while degraded (state)
I_MON_OK = IV.slot()  # consecutive ticks below the re-arm level (state)
I_MON_BAD = IV.slot()  # consecutive ticks with an unusable estimate (state)
I_MON_NDEG = IV.slot()  # degradations since reset (state)
I_MON_DEGTICKS = IV.slot()  # ticks spent degraded since reset (state)
I_SB_TICKS = IV.slot()  # ticks in which the end-stop barrier changed the force since reset (state)
I_GUARD_TICKS = IV.slot()  # ticks in which the end-stop guard took force away since reset (state)
I_GUARD_LEAD_TICKS = IV.slot()  # ... of them, ticks the rate lead took more than distance (state)
# --- iv: stop-contact monitor (docs/design.md §9.8)
I_SC_ON = IV.slot()  # 1: degrade above the budget; 0: report only
I_SC_RECOVER = IV.slot()  # ticks below the re-arm level needed to re-arm
I_SC_GAP = IV.slot()  # ticks without contact that end an episode
I_SC_DEG = IV.slot()  # 1 while stop-degraded (state)
I_SC_OK = IV.slot()  # consecutive ticks below the re-arm level (state)
I_SC_QUIET = IV.slot()  # ticks since the last contact tick (state)
I_SC_TICKS = IV.slot()  # contact ticks since reset (state)
I_SC_EPISODES = IV.slot()  # contact episodes since reset (state)
I_SC_NDEG = IV.slot()  # stop degradations since reset (state)
I_SC_DEGTICKS = IV.slot()  # ticks spent stop-degraded since reset (state)
I_RH_OFF = IV.slot()  # 1 while the body is off centre (ride-height monitor; state)
# --- iv: sprung-mass layers (controller/runtime/mass_layers.py)
I_NLAYER = IV.slot()  # number of sprung-mass layers (1: no scheduling)
I_NTIRE = IV.slot()  # on-ground models per layer (model j of layer l is l * NTIRE + t)
I_LAYER0 = IV.slot()  # layer after a reset (nearest the configured mass)
I_SINGLE0 = IV.slot()  # single model after a reset
I_LDWELL = IV.slot()  # ticks a layer is kept at least
I_LAYER = IV.slot()  # layer the bank runs (state)
I_LCAND = IV.slot()  # layer the estimate prefers to the running one (state)
I_LSINCE = IV.slot()  # ticks I_LCAND has been preferred in a row (state)
I_NLAYERSW = IV.slot()  # layer changes since reset (state)
# --- iv: road preview (controller/road_preview.py)
I_PVCALL = IV.slot()  # 1: the road preview called the travel law in the last previewed tick (state)
I_PVCLAMP = IV.slot()  # stop clamp for the next step: 1 = F_PVC_FMIN/FMAX bound it (state)
I_PVCHECKED = IV.slot()  # the stop clamp checked for the next step (state; the step clears it)
I_PVCLAMP_TICKS = IV.slot()  # ticks in which the stop clamp clipped the force since reset (state)
IV_ACT = IV.size  # iv[IV_ACT : IV_ACT + I_NACT]: the running filters, ascending
IV_HEAD = IV.size  # iv has IV_HEAD + J entries

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
    _clear_outputs(st, j)
    st[j, S_P] = p0


@nb.njit(cache=True, nogil=True)
def _clear_outputs(st: np.ndarray, j: int) -> None:
    """Zero model j's per-tick outputs: q, firing weight, probability, control,
    force, contribution flag and bad-estimate count."""
    for c in (S_Q, S_W, S_P, S_U, S_F, S_CONTRIB, S_BAD):
        st[j, c] = 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def filtered_rate(fv: np.ndarray, rattlespace_m: float) -> float:
    """The force loop's filtered LVDT rate r' [m/s, compression positive] this tick: the
    rate filter's state w (F_FFW, before :func:`servo_update` advances it) plus b times
    the reading (``FlowFeedforward.rate_mps``); NaN before the first reading."""
    return fv[F_FFW] + fv[F_FFB] * rattlespace_m


@nb.njit(cache=True, nogil=True)
def stop_guard(fv: np.ndarray, iv: np.ndarray, force_n: float, rattlespace_m: float) -> float:
    """The force after the end-stop guard (controller/stop_guard.py): a force toward a
    bump stop fades linearly to 0 over the last ``F_GUARD_W`` metres before it, the
    reading led by ``F_GUARD_LEAD`` times the approach rate above ``F_GUARD_V0`` (the force
    loop's filtered LVDT rate, F_FFW, before :func:`servo_update` advances it this tick);
    under the travel schedule the lead is scaled by the comfort share β of this tick
    (docs/design.md §9.6).  The factor is kept in ``F_GUARD_S``; the ticks in which it
    took force away are counted in ``I_GUARD_TICKS``, those in which the lead took more
    than the distance law alone would have in ``I_GUARD_LEAD_TICKS``."""
    w = fv[F_GUARD_W]
    s = 1.0
    if w > 0.0:
        lead = fv[F_GUARD_LEAD]
        if fv[F_TS_ON] != 0.0:
            lead *= fv[F_TS_BETA]
        rate = filtered_rate(fv, rattlespace_m)
        if not math.isfinite(rate):
            rate = 0.0
        v0 = fv[F_GUARD_V0]
        d = 1.0                         # the distance law's factor (for the count)
        if force_n < 0.0:
            s = (fv[F_BS_HI] - rattlespace_m - lead * max(rate - v0, 0.0)) / w
            d = (fv[F_BS_HI] - rattlespace_m) / w
        elif force_n > 0.0:
            s = (rattlespace_m - fv[F_BS_LO] - lead * max(-rate - v0, 0.0)) / w
            d = (rattlespace_m - fv[F_BS_LO]) / w
        s = min(max(s, 0.0), 1.0)
        if s < 1.0:
            iv[I_GUARD_TICKS] += 1
            if s < min(max(d, 0.0), 1.0):
                iv[I_GUARD_LEAD_TICKS] += 1
    fv[F_GUARD_S] = s
    return force_n * s


@nb.njit(cache=True, nogil=True, inline="always")
def degrade_or_rearm(iv: np.ndarray, i_deg: int, i_ok: int, i_ndeg: int, i_recover: int,
                     level: float, degrade_above: float, rearm_below: float,
                     may_degrade: bool) -> None:
    """A monitor's degrade / re-arm hysteresis, once per tick (the estimator monitor's
    and the stop-contact monitor's): armed (``iv[i_deg]`` 0), it degrades when ``level``
    exceeds ``degrade_above`` (and ``may_degrade``), counting in ``iv[i_ndeg]``; degraded,
    it re-arms once ``level`` stayed below ``rearm_below`` for ``iv[i_recover]`` ticks in
    a row (``iv[i_ok]`` counts them)."""
    if iv[i_deg] == 0:
        if level > degrade_above and may_degrade:
            iv[i_deg] = 1
            iv[i_ok] = 0
            iv[i_ndeg] += 1
    elif level < rearm_below:
        iv[i_ok] += 1
        if iv[i_ok] >= iv[i_recover]:
            iv[i_deg] = 0
    else:
        iv[i_ok] = 0


@nb.njit(cache=True, nogil=True, inline="always")
def ramp_authority(fv: np.ndarray, slot: int, degraded: bool, floor: float) -> None:
    """A monitor's force authority ``fv[slot]``, once per tick: down by ``F_AUTH_STEP``
    toward ``floor`` while degraded, back up toward 1 after."""
    auth = fv[slot]
    if degraded:
        auth -= fv[F_AUTH_STEP]
        fv[slot] = auth if auth > floor else floor
    else:
        auth += fv[F_AUTH_STEP]
        fv[slot] = auth if auth < 1.0 else 1.0


@nb.njit(cache=True, nogil=True, inline="always")
def stop_contact(fv: np.ndarray, iv: np.ndarray, rattlespace_m: float) -> int:
    """The stop-contact monitor, once per tick (controller/stop_contact.py): contact
    time in the exponential window ``F_SC_TIME``, episodes, degrade above ``F_SC_BUDGET``
    (when ``I_SC_ON``), re-arm after ``I_SC_RECOVER`` ticks below ``F_SC_REARM``; the
    monitor's force authority ``F_SC_AUTH`` ramps toward ``F_SC_FLOOR`` while degraded and
    back to 1 after (the estimator monitor's step ``F_AUTH_STEP``).  Returns the flag bits
    (STOP_DEGRADED, STOP_CONTACT)."""
    flags = 0
    band = fv[F_SC_BAND]
    e = fv[F_SC_DECAY] * fv[F_SC_TIME]
    if rattlespace_m > fv[F_BS_HI] - band or rattlespace_m < fv[F_BS_LO] + band:
        e += fv[F_SC_TICK]
        iv[I_SC_TICKS] += 1
        if iv[I_SC_QUIET] >= iv[I_SC_GAP]:
            iv[I_SC_EPISODES] += 1
        iv[I_SC_QUIET] = 0
    elif iv[I_SC_QUIET] < iv[I_SC_GAP]:
        iv[I_SC_QUIET] += 1
    if iv[I_SC_QUIET] < iv[I_SC_GAP]:
        flags |= _STOP_CONTACT
    fv[F_SC_TIME] = e
    degrade_or_rearm(iv, I_SC_DEG, I_SC_OK, I_SC_NDEG, I_SC_RECOVER, e, fv[F_SC_BUDGET],
                     fv[F_SC_REARM], iv[I_SC_ON] != 0)
    degraded = iv[I_SC_DEG] != 0
    if degraded:
        flags |= _STOP_DEGRADED
        iv[I_SC_DEGTICKS] += 1
    ramp_authority(fv, F_SC_AUTH, degraded, fv[F_SC_FLOOR])
    return flags


@nb.njit(cache=True, nogil=True)
def ride_height(fv: np.ndarray, iv: np.ndarray, rattlespace_m: float) -> int:
    """The ride-height monitor, once per tick (controller/ride_height.py): the exponential
    mean ``F_RH`` of the LVDT reading about the stops' centre, off centre (``I_RH_OFF``)
    above ``F_RH_WARN`` until below ``F_RH_CLEAR``.  Returns the flag bit (RIDE_HEIGHT)."""
    x = rattlespace_m - fv[F_RH_CENTRE]
    if not math.isfinite(x):
        return _RIDE_HEIGHT if iv[I_RH_OFF] != 0 else 0
    h = fv[F_RH] + fv[F_RH_ALPHA] * (x - fv[F_RH])
    fv[F_RH] = h
    if fv[F_RH_WARN] <= 0.0:
        iv[I_RH_OFF] = 0
    elif iv[I_RH_OFF] != 0:
        if abs(h) < fv[F_RH_CLEAR]:
            iv[I_RH_OFF] = 0
    elif abs(h) > fv[F_RH_WARN]:
        iv[I_RH_OFF] = 1
    return _RIDE_HEIGHT if iv[I_RH_OFF] != 0 else 0


@nb.njit(cache=True, nogil=True, inline="always")
def _barrier_bound(fv: np.ndarray, distance_m: float, approach_mps: float,
                   passive_toward_n: float) -> tuple[float, float]:
    """(largest admissible force toward a stop [N], barrier h [m]): the kernel of
    ``controller.stop_barrier.force_bound_toward_stop``."""
    mass = fv[F_SB]
    a = fv[F_SB + 4] / mass
    lag = fv[F_SB + 5]
    vp = max(approach_mps, 0.0)
    d = fv[F_SB + 8]                    # worst case: least help, most push
    passive_toward_n *= (1.0 + d) if passive_toward_n > 0.0 else (1.0 - d)
    h = distance_m - fv[F_SB + 3] - vp * vp / (2.0 * a) - lag * vp
    bound = mass * (fv[F_SB + 6] * h - vp) / (lag + vp / a) - passive_toward_n
    return max(bound, -fv[F_SB + 4]), h


@nb.njit(cache=True, nogil=True)
def stop_barrier(fv: np.ndarray, iv: np.ndarray, force_n: float, rattlespace_m: float) -> float:
    """The force after the end-stop barrier (controller/stop_barrier.py, docs/design.md
    §9.7): the law's force clipped to what keeps the braking-distance barrier of both
    stops; the rattlespace rate is the force loop's filtered LVDT rate (F_FFW, advanced
    later in the tick by :func:`servo_update`) low-passed once more (F_SB_V).  The change
    is kept in ``F_SB_DF``, the ticks with a change are counted in ``I_SB_TICKS``."""
    fv[F_SB_DF] = 0.0
    if not (fv[F_SB] > 0.0):
        return force_n
    rate = filtered_rate(fv, rattlespace_m)
    if math.isnan(fv[F_SB_V]):
        fv[F_SB_V] = rate
    rate = fv[F_SB_V] + fv[F_SB + 7] * (rate - fv[F_SB_V])
    if math.isfinite(rate):
        fv[F_SB_V] = rate
    passive = fv[F_SB + 1] * rattlespace_m + fv[F_SB + 2] * rate
    u_hi, h_hi = _barrier_bound(fv, fv[F_BS_HI] - rattlespace_m, rate, -passive)
    u_lo, h_lo = _barrier_bound(fv, rattlespace_m - fv[F_BS_LO], -rate, passive)
    f_min = -u_hi
    f_max = u_lo
    out = min(max(force_n, f_min), f_max)
    if f_min > f_max:                   # the bounds cross: the nearer stop wins
        out = f_min if h_hi <= h_lo else f_max
    if out != force_n and math.isfinite(out):
        fv[F_SB_DF] = out - force_n
        iv[I_SB_TICKS] += 1
        return out
    return force_n


@nb.njit(cache=True, nogil=True, inline="always")
def travel_comfort_share(fv: np.ndarray, rattlespace_m: float) -> float:
    """beta, the comfort law's share of this tick's force under the travel schedule
    (controller/travel_schedule.py, docs/design.md §12); 0 when the schedule is off."""
    if fv[F_TS_ON] == 0.0:
        fv[F_TS_BETA] = 0.0
        return 0.0
    usage = abs(rattlespace_m - fv[F_TS])
    env = fv[F_TS_ENV] * fv[F_TS + 3]
    if usage > env or not math.isfinite(env):
        env = usage
    if math.isfinite(env):
        fv[F_TS_ENV] = env
    x = (env - fv[F_TS + 1]) * fv[F_TS + 2]
    x = min(max(x, 0.0), 1.0)
    beta = 1.0 - x * x * (3.0 - 2.0 * x)
    if not math.isfinite(beta):
        beta = 0.0
    fv[F_TS_BETA] = beta
    return beta


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
    _clear_outputs(st, j)


@nb.njit(cache=True, nogil=True)
def servo_update(fv: np.ndarray, nd: int, force_ref_n: float, force_meas_n: float,
                 rattlespace_m: float) -> None:
    """Advance the spool model by one tick after the force reference went out:
    s_k = clip(kp (clip(fref) - F_meas) + s_ff), the valve gets s_{k-D}, x̂_v follows it
    (ZOH).  s_ff is the force loop's flow feedforward (``FlowFeedforward.step``), its
    rate-filter state w (F_FFW) advanced here; the caller initialises a NaN w."""
    b = fv[F_FFB]
    rho = filtered_rate(fv, rattlespace_m)
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


@nb.njit(cache=True, nogil=True, inline="always")
def _biquad(fv: np.ndarray, c: int, s: int, x: float) -> float:
    """Direct form II transposed biquad: coefficients fv[c:c+5] (b0, b1, b2, a1, a2),
    state fv[s:s+2]."""
    y = fv[c] * x + fv[s]
    fv[s] = fv[c + 1] * x - fv[c + 3] * y + fv[s + 1]
    fv[s + 1] = fv[c + 2] * x - fv[c + 4] * y
    return y


@nb.njit(cache=True, nogil=True, inline="always")
def _hp_at_rest(fv: np.ndarray, hp: int, s: int, x: float) -> None:
    """A high-pass state ``fv[s:s+2]`` at steady state for the constant input ``x``."""
    fv[s] = (fv[hp + 1] + fv[hp + 2]) * x
    fv[s + 1] = fv[hp + 2] * x


@nb.njit(cache=True, nogil=True, inline="always")
def _body_fit(fv: np.ndarray, p: int, s: int) -> None:
    """θ = [M, K, C] from the information of the state and the prior on K and C
    (Cholesky of the 3 x 3 system, ``controller.mass_estimator.solve_body_fit``'s
    arithmetic); clamped, and left unchanged if the system is not positive definite."""
    r00 = fv[s + ME_SAA]
    if not r00 > 0.0:
        return
    r11 = fv[s + ME_RZZ] + fv[p + ME_WK]
    r22 = fv[s + ME_RVV] + fv[p + ME_WC]
    b1 = fv[s + ME_BZ] + fv[p + ME_WK] * fv[p + ME_K]
    b2 = fv[s + ME_BV] + fv[p + ME_WC] * fv[p + ME_C]
    l00 = math.sqrt(r00)
    l10 = fv[s + ME_RAZ] / l00
    l20 = fv[s + ME_RAV] / l00
    d1 = r11 - l10 * l10
    if not d1 > 0.0:
        return
    l11 = math.sqrt(d1)
    l21 = (fv[s + ME_RZV] - l20 * l10) / l11
    d2 = r22 - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return
    l22 = math.sqrt(d2)
    y0 = fv[s + ME_SAY] / l00
    y1 = (b1 - l10 * y0) / l11
    y2 = (b2 - l20 * y0 - l21 * y1) / l22
    c = y2 / l22
    k = (y1 - l21 * c) / l11
    m = (y0 - l10 * k - l20 * c) / l00
    if not (math.isfinite(m) and math.isfinite(k) and math.isfinite(c)):
        return
    lo = fv[p + ME_LO] / fv[p + ME_M0]
    hi = fv[p + ME_HI] / fv[p + ME_M0]
    fv[s + ME_EST] = min(max(m, fv[p + ME_LO]), fv[p + ME_HI])
    fv[s + ME_KEST] = min(max(k, lo * fv[p + ME_K]), hi * fv[p + ME_K])
    fv[s + ME_CEST] = min(max(c, lo * fv[p + ME_C]), hi * fv[p + ME_C])
    fv[s + ME_NUPD] += 1.0


@nb.njit(cache=True, nogil=True, inline="always")
def mass_estimate(fv: np.ndarray, force_n: float, rattlespace_m: float,
                  accel_mps2: float, contacts_rare: bool) -> None:
    """One tick of the sprung-mass estimator (controller/mass_estimator.py, the plain
    reference ``MassEstimator``): band-passed least squares with forgetting on
    F + F_bs = M a - K z - C z' for [M, K, C] with a weak prior on K and C, without
    the samples near an isolated stop contact (``contacts_rare``: the stop-contact
    window is within its budget); the estimates in ``fv[F_MES + ME_EST]`` (M),
    ``ME_KEST`` (K), ``ME_CEST`` (C)."""
    p = F_ME
    s = F_MES
    if not (fv[p + ME_LAMBDA] > 0.0):      # off: the estimate stays the configured mass
        return
    hp = p + ME_HP
    lp = p + ME_LP
    if math.isnan(fv[s + ME_ZPREV]):        # first sample: the high-passes at steady state
        fv[s + ME_ZPREV] = rattlespace_m
        fv[s + ME_APREV] = accel_mps2
        fv[s + ME_FPREV] = force_n
        _hp_at_rest(fv, hp, s + ME_HPA, accel_mps2)
        _hp_at_rest(fv, hp, s + ME_HPY, force_n)
        _hp_at_rest(fv, hp, s + ME_HPZ, rattlespace_m)
        _hp_at_rest(fv, hp, s + ME_HPV, 0.0)
    # the velocity half a tick ago, and the other signals at that instant
    zdot = (rattlespace_m - fv[s + ME_ZPREV]) * fv[p + ME_INV_DT]
    a_mid = 0.5 * (accel_mps2 + fv[s + ME_APREV])
    f_mid = 0.5 * (force_n + fv[s + ME_FPREV])
    z_mid = 0.5 * (rattlespace_m + fv[s + ME_ZPREV])
    fv[s + ME_ZPREV] = rattlespace_m
    fv[s + ME_APREV] = accel_mps2
    fv[s + ME_FPREV] = force_n
    pa = _biquad(fv, lp, s + ME_LPA, _biquad(fv, hp, s + ME_HPA, a_mid))
    yb = _biquad(fv, lp, s + ME_LPY, _biquad(fv, hp, s + ME_HPY, f_mid))
    pz = -_biquad(fv, lp, s + ME_LPZ, _biquad(fv, hp, s + ME_HPZ, z_mid))
    pv = -_biquad(fv, lp, s + ME_LPV, _biquad(fv, hp, s + ME_HPV, zdot))
    if contacts_rare and not (fv[p + ME_STOP_LO] < rattlespace_m < fv[p + ME_STOP_HI]):
        fv[s + ME_HOLD] = fv[p + ME_HOLD_TICKS]     # an isolated stop contact: F_bs unsure
    if fv[s + ME_NSEEN] < fv[p + ME_SETTLE]:    # the band-pass settling after a reset
        fv[s + ME_NSEEN] += 1.0
        return
    w = 1.0                                     # weight of this sample in the fit
    if fv[s + ME_HOLD] > 0.0:                   # near an isolated contact: none (the old
        fv[s + ME_HOLD] -= 1.0                  # data keep fading)
        w = 0.0
    lam = fv[p + ME_LAMBDA]
    saa = lam * fv[s + ME_SAA] + w * pa * pa
    if not (math.isfinite(saa) and math.isfinite(yb) and math.isfinite(pz)
            and math.isfinite(pv)):         # restart the fit
        fv[s + ME_ZPREV] = np.nan
        for i in (ME_SAA, ME_RAZ, ME_RAV, ME_RZZ, ME_RZV, ME_RVV, ME_SAY, ME_BZ, ME_BV):
            fv[s + i] = 0.0
        return
    fv[s + ME_SAA] = saa
    fv[s + ME_RAZ] = lam * fv[s + ME_RAZ] + w * pa * pz
    fv[s + ME_RAV] = lam * fv[s + ME_RAV] + w * pa * pv
    fv[s + ME_RZZ] = lam * fv[s + ME_RZZ] + w * pz * pz
    fv[s + ME_RZV] = lam * fv[s + ME_RZV] + w * pz * pv
    fv[s + ME_RVV] = lam * fv[s + ME_RVV] + w * pv * pv
    fv[s + ME_SAY] = lam * fv[s + ME_SAY] + w * pa * yb
    fv[s + ME_BZ] = lam * fv[s + ME_BZ] + w * pz * yb
    fv[s + ME_BV] = lam * fv[s + ME_BV] + w * pv * yb
    if saa > fv[p + ME_SMIN]:
        _body_fit(fv, p, s)


@nb.njit(cache=True, nogil=True)
def mass_estimate_reset(fv: np.ndarray) -> None:
    """The estimator's state after a reset: no data, the estimates the configured mass,
    spring rate and damping."""
    s = F_MES
    for i in range(ME_STATE_SIZE):
        fv[s + i] = 0.0
    fv[s + ME_ZPREV] = np.nan
    fv[s + ME_EST] = fv[F_ME + ME_M0]
    fv[s + ME_KEST] = fv[F_ME + ME_K]
    fv[s + ME_CEST] = fv[F_ME + ME_C]


@nb.njit(cache=True, nogil=True, inline="always")
def _wheel_hop_scale(fv: np.ndarray, f_hz: float) -> float:
    """The tire stiffness scale the table of ``F_WH`` gives for the passive wheel-hop
    frequency ``f_hz`` (interpolated in logs; NaN outside the table)."""
    p = F_WH
    n = WH_TAB_S - WH_TAB_F
    lf = math.log(f_hz)
    if not (fv[p + WH_TAB_F] <= lf <= fv[p + WH_TAB_F + n - 1]):
        return np.nan
    i = 0
    while i < n - 2 and fv[p + WH_TAB_F + i + 1] < lf:
        i += 1
    f0 = fv[p + WH_TAB_F + i]
    f1 = fv[p + WH_TAB_F + i + 1]
    s0 = fv[p + WH_TAB_S + i]
    s1 = fv[p + WH_TAB_S + i + 1]
    return math.exp(s0 + (s1 - s0) * (lf - f0) / (f1 - f0))


@nb.njit(cache=True, nogil=True, inline="always")
def wheel_hop_track(fv: np.ndarray, rattlespace_m: float, force_n: float) -> None:
    """One tick of the wheel-hop tracker (controller/wheel_hop.py): the LVDT reading
    band-passed twice, every ``WH_STEP``-th sample of a passive stretch into an AR(2)
    least squares with forgetting; the passive wheel-hop frequency in
    ``fv[F_WHS + WHS_HZ]`` [Hz] and the tire stiffness scale in ``WHS_SCALE`` (NaN
    until the rig has been passive and moving enough; held otherwise)."""
    p = F_WH
    s = F_WHS
    if not (fv[p + WH_ON] > 0.0):
        return
    y = rattlespace_m
    for k in range(4):                  # two passes of two sections
        y = _biquad(fv, p + WH_SOS + 5 * (k % 2), s + WHS_BP + 2 * k, y)
    env = max(abs(force_n), fv[p + WH_FDECAY] * fv[s + WHS_FENV])
    fv[s + WHS_FENV] = env if math.isfinite(env) else 0.0
    if not math.isfinite(y):            # restart the band-pass
        for i in range(8):
            fv[s + WHS_BP + i] = 0.0
    if not (math.isfinite(y) and env < fv[p + WH_FMAX]):
        fv[s + WHS_NPASS] = 0.0         # not passive: the sums hold, the chain restarts
        fv[s + WHS_COUNT] = 0.0
        return
    fv[s + WHS_NPASS] += 1.0
    settle = fv[p + WH_SETTLE]
    if fv[s + WHS_NPASS] <= settle:
        return
    fv[s + WHS_COUNT] += 1.0
    step = fv[p + WH_STEP]
    if fv[s + WHS_COUNT] < step:
        return
    fv[s + WHS_COUNT] = 0.0
    y1 = fv[s + WHS_Y1]
    y2 = fv[s + WHS_Y2]
    fv[s + WHS_Y2] = y1
    fv[s + WHS_Y1] = y
    if fv[s + WHS_NPASS] < settle + 3.0 * step:
        return                          # not two samples of this stretch before it yet
    lam = fv[p + WH_LAMBDA]
    r11 = lam * fv[s + WHS_R11] + y1 * y1
    r12 = lam * fv[s + WHS_R12] + y1 * y2
    r22 = lam * fv[s + WHS_R22] + y2 * y2
    b1 = lam * fv[s + WHS_B1] + y1 * y
    b2 = lam * fv[s + WHS_B2] + y2 * y
    nwin = lam * fv[s + WHS_NWIN] + 1.0
    fv[s + WHS_R11] = r11
    fv[s + WHS_R12] = r12
    fv[s + WHS_R22] = r22
    fv[s + WHS_B1] = b1
    fv[s + WHS_B2] = b2
    fv[s + WHS_NWIN] = nwin
    if not (nwin >= fv[p + WH_NMIN] and r11 > fv[p + WH_RMIN] * nwin):
        return                          # too little passive data, or a quiet rig: hold
    det = r11 * r22 - r12 * r12
    if not det > 0.0:
        return
    f = ar2_frequency_hz((b1 * r22 - b2 * r12) / det, (b2 * r11 - b1 * r12) / det,
                         fv[p + WH_TFIT], fv[p + WH_LO], fv[p + WH_HI])
    if math.isnan(f):
        return                          # not a damped oscillation within the band
    fv[s + WHS_HZ] = f
    fv[s + WHS_SCALE] = _wheel_hop_scale(fv, f)
    fv[s + WHS_NUPD] += 1.0


@nb.njit(cache=True, nogil=True)
def wheel_hop_reset(fv: np.ndarray) -> None:
    """The tracker's state after a reset: no data, no estimate (NaN)."""
    s = F_WHS
    for i in range(WH_STATE_SIZE):
        fv[s + i] = 0.0
    fv[s + WHS_HZ] = np.nan
    fv[s + WHS_SCALE] = np.nan
