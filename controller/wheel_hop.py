"""Wheel-hop frequency of a run from its LVDT reading: a resonance fit (docs/design.md §11).

The tire is not a layer axis of the bank, and the bank's residuals do not tell a soft
tire from a stiff one (docs/design.md §11).  The wheel hop does: its frequency moves
with the tire's stiffness (about sqrt((K + Kt) / m)), and the LVDT reading (the
rattlespace, wheel minus body) carries it.  The fit:

1. band-pass the reading at ``band_hz`` (2nd-order Butterworth, run forward and
   backward: no phase lag, the body mode and the sensor noise above the band out);
2. decimate to about ``fit_rate_hz`` (the band is well inside its Nyquist frequency);
3. fit an AR(2) model  y_k = a1 y_{k-1} + a2 y_{k-2}  by least squares over the samples
   of ``mask``; its complex pole pair p gives the frequency  angle(p) / (2 pi T_fit).

The model is of order 2 (one resonance): higher orders fit the band-pass's own poles,
which are less damped than a wheel hop.  The fit compares runs; it is not an absolute
measurement.  The band-pass colours the
noise that drives the fit's residual, which pulls the estimate toward the band's centre
(10 Hz): on a white-noise-driven oscillator with damping ratio 0.2, +12 % at 7 Hz, +2 % at
10 Hz, -4 % at 13 Hz (tests/test_wheel_hop.py).  A wider band or a higher order was
worse on the emulated rig (the road's and the body's content, the band-pass's own
poles).  Measured there (road seeds 1-3 of the thesis course, 28 s): 8.7 / 9.4 / 10.1
Hz for a tire 0.7 / 1 / 1.3 x as stiff under passive, within 0.06 Hz over the seeds
(10 s: within 0.3 Hz).  The law moves it (the default law: 9.0 / 10.0 / 10.6 Hz), so it
is the closed loop's wheel hop: compare runs under the same law, or with the design's
closed-loop mode, not with sqrt((K + Kt) / m).  Pure numpy / scipy; NaN where no fit is
possible.

What the fit reads on the passive rig can be predicted (:func:`passive_wheel_hop_hz`):
the fit's least-squares AR(2) tends to the Yule-Walker solution on the autocovariance of
the band-passed reading, and that of the linear quarter car at its static tire
deflection (the tire's tangent stiffness e f_k(x2) / x2 there, its damping Ct(x2)),
driven by a road whose velocity is white, comes from one discrete Lyapunov equation.
It predicts the bias toward the band's centre with the rest: 8.69 / 9.49 / 10.21 Hz for
a tire 0.7 / 1 / 1.3 x as stiff, against 8.67 / 9.46 / 10.16 Hz fitted on the emulated
rig's passive runs (thesis course; ISO B road 8.68 / 9.48 / 10.22).  Inverted
(:func:`tire_stiffness_scale`), a passive stretch of the LVDT gives the tire's stiffness
against the configured one: the frequency goes about as the scale^0.23, so 0.05 Hz is
about 2 % of stiffness.  The prediction takes the configured M, m, K and C: a rig that
differs there reads as a tire that differs (docs/design.md §11).

The runtime tracks the same fit while the rig is passive
(``controller.runtime.kernels.wheel_hop_track``, parameters
:func:`wheel_hop_tracker_parameters`): the band-pass run twice forward (the spectrum of
forward-backward, so the same prediction holds), every ``fs // fit_rate_hz``-th sample
kept (the offline fit's decimation), and the AR(2) least squares with exponential
forgetting over :data:`TRACK_WINDOW_S`.  It takes
samples only while the load cell reads no force (its envelope, :data:`FORCE_RELEASE_S`
release, below :data:`PASSIVE_FORCE_N`: the valve is safe, the suspension is the passive one the
prediction is of) and :data:`TRACK_SETTLE_S` after that began, and gives an estimate
once :data:`TRACK_MIN_DATA_S` of such samples are in the window and their band-passed
mean square is :data:`TRACK_SNR` ² x the band-passed LVDT noise's (a quiet rig's
reading is noise, whose fit is the band's centre); otherwise it holds the last one.
The tire's stiffness it publishes follows from a table of the prediction over
:data:`TIRE_SCALE_RANGE` for the configured rig, interpolated in logs; the bank's tire
layers compare the frequency itself with each layer's own prediction
(``controller.runtime.bank``), so a layer's M, K and C do not read as its tire.
"""

from __future__ import annotations

import functools
import math

import numba as nb
import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.signal import butter, cont2discrete, sosfilt, sosfiltfilt, zpk2ss

from controller.arrays import FloatArray
from controller.config import RigConfig, TireConfig, VehicleConfig, layer_config
from controller.plant import (
    linear_model,
    static_tire_deflection_m,
    tire_damping_ns_per_m,
    tire_secant_stiffness_n_per_m,
)

__all__ = ["MIN_FIT_S", "TIRE_SCALE_RANGE", "WH_SIZE", "WH_STATE_SIZE", "ar2_frequency_hz",
           "passive_wheel_hop_hz", "tire_stiffness_scale", "wheel_hop_frequency_hz",
           "wheel_hop_tracker_parameters"]

#: tire stiffness scales (x ``tire.stiffness_coefficient``) :func:`tire_stiffness_scale`
#: searches; a frequency outside their predictions gives NaN
TIRE_SCALE_RANGE = (0.25, 4.0)

#: forgetting time of the runtime's fit [s]
TRACK_WINDOW_S = 20.0
#: the rig is passive while the load cell's |force| envelope (0.5 s release) is below this [N]
PASSIVE_FORCE_N = 200.0
#: release time of the load cell's |force| envelope [s]
FORCE_RELEASE_S = 0.5
#: samples are taken this long after the rig became passive [s] (the band-pass settles)
TRACK_SETTLE_S = 0.5
#: an estimate needs this much passive data in the window [s]
TRACK_MIN_DATA_S = 8.0
#: ... and the band-passed reading's RMS this many times the band-passed sensor noise's
TRACK_SNR = 5.0
#: points of the frequency-to-stiffness table
TABLE_POINTS = 25

# parameter layout (wheel_hop_tracker_parameters)
(WH_ON, WH_STEP, WH_LAMBDA, WH_FDECAY, WH_FMAX, WH_SETTLE, WH_NMIN, WH_RMIN, WH_TFIT,
 WH_LO, WH_HI) = range(11)
WH_SOS = 11                         # band-pass sections: 2 x (b0, b1, b2, a1, a2)
WH_TAB_F = WH_SOS + 10              # log of the predicted frequency at each table point
WH_TAB_S = WH_TAB_F + TABLE_POINTS  # log of the tire stiffness scale at each table point
WH_SIZE = WH_TAB_S + TABLE_POINTS
# state layout: band-pass states (2 passes x 2 sections x 2), the decimation count, the
# last two kept samples, the information (r11, r12, r22) and vector (b1, b2), the force
# envelope, ticks passive, samples in the window (forgetting), the estimates
WHS_BP = 0
(WHS_COUNT, WHS_Y1, WHS_Y2, WHS_R11, WHS_R12, WHS_R22, WHS_B1, WHS_B2, WHS_FENV,
 WHS_NPASS, WHS_NWIN, WHS_HZ, WHS_SCALE, WHS_NUPD) = range(8, 22)
WH_STATE_SIZE = 22

#: shortest stretch of readings [s] a fit is made from (a few hundred wheel-hop cycles)
MIN_FIT_S = 5.0


def wheel_hop_frequency_hz(rattlespace_m: FloatArray, dt_s: float,
                           mask: NDArray[np.bool_] | None = None, *,
                           band_hz: tuple[float, float] = (5.0, 20.0),
                           fit_rate_hz: float = 200.0) -> float:
    """The wheel-hop frequency [Hz] of the LVDT readings ``rattlespace_m`` [m] sampled
    every ``dt_s`` [s], fitted over the ticks of ``mask`` (default: all).  NaN when the
    band does not fit below the sampling's Nyquist frequency, when fewer than
    :data:`MIN_FIT_S` seconds of finite readings fall in ``mask``, or when the fitted
    poles are not a damped oscillation within the band."""
    x = np.asarray(rattlespace_m, dtype=float)
    lo, hi = band_hz
    fs = 1.0 / dt_s
    if not (0.0 < lo < hi < 0.5 * fs) or x.size == 0:
        return math.nan
    m = np.ones(x.size, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    finite = np.isfinite(x)
    m = m & finite
    if np.count_nonzero(m) * dt_s < MIN_FIT_S:
        return math.nan
    x = np.where(finite, x, 0.0)
    x = x - np.mean(x[m])
    sos = butter(2, [lo, hi], btype="band", fs=fs, output="sos")
    y = sosfiltfilt(sos, x)
    step = max(1, int(fs // fit_rate_hz))
    yd, md = y[::step], m[::step]
    rows = md[2:] & md[1:-1] & md[:-2]          # all three samples of a row in the mask
    if np.count_nonzero(rows) < 6:
        return math.nan
    regressors = np.column_stack([yd[1:-1][rows], yd[:-2][rows]])
    a1, a2 = np.linalg.lstsq(regressors, yd[2:][rows], rcond=None)[0]
    return float(ar2_frequency_hz.py_func(float(a1), float(a2), dt_s * step, lo, hi))


@nb.njit(nogil=True, inline="always")
def ar2_frequency_hz(a1: float, a2: float, t_fit_s: float, lo_hz: float,
                     hi_hz: float) -> float:
    """Frequency [Hz] of the AR(2)  y_k = a1 y_{k-1} + a2 y_{k-2}  sampled every
    ``t_fit_s`` [s]: the angle of its pole pair; NaN unless the poles are a damped
    oscillation (complex, a1² + 4 a2 < 0, inside the unit circle, |p|² = -a2 < 1) at a
    frequency within [``lo_hz``, ``hi_hz``].  The one statement of this rule: the
    offline fits call it as plain Python (``ar2_frequency_hz.py_func``), the runtime's
    tracker compiled into the bank's step."""
    if not (a1 * a1 + 4.0 * a2 < 0.0 and 0.0 < -a2 < 1.0):
        return math.nan
    f = math.acos(max(-1.0, min(1.0, a1 / (2.0 * math.sqrt(-a2))))) / (
        2.0 * math.pi * t_fit_s)
    return f if lo_hz <= f <= hi_hz else math.nan


def passive_wheel_hop_hz(cfg: RigConfig, *, dt_s: float | None = None,
                         band_hz: tuple[float, float] = (5.0, 20.0),
                         fit_rate_hz: float = 200.0) -> float:
    """What :func:`wheel_hop_frequency_hz` reads [Hz] on a long passive run of the rig
    ``cfg`` (its vehicle and tire; LVDT sampled every ``dt_s``, default the loop's
    ``cfg.sample_time_s``), a road whose velocity is white driving it.  The linear quarter
    car at the static tire deflection x2 (tire stiffness e f_k(x2) / x2, the tangent;
    damping Ct(x2)) is discretised with the band-pass twice after it (forward and
    backward have the spectrum of twice forward), its state covariance solved from the
    discrete Lyapunov equation, and the fit's AR(2) taken from the Yule-Walker equations
    on the autocovariance at the fit's lags.  NaN where the fit would be."""
    dt = cfg.sample_time_s if dt_s is None else dt_s
    return _passive_wheel_hop_hz(cfg.vehicle, cfg.tire, static_tire_deflection_m(cfg),
                                 float(dt), (float(band_hz[0]), float(band_hz[1])),
                                 float(fit_rate_hz))


@functools.lru_cache(maxsize=4096)
def _passive_wheel_hop_hz(vehicle: VehicleConfig, tire: TireConfig, x2: float, dt: float,
                          band_hz: tuple[float, float], fit_rate_hz: float) -> float:
    """:func:`passive_wheel_hop_hz` of the rig (``vehicle``, ``tire``) at the static tire
    deflection ``x2`` [m]; remembered (a bank with tire layers asks for each of its
    layers' rigs whenever a runtime is built, ~1 ms each)."""
    fs = 1.0 / dt
    lo, hi = band_hz
    if not (0.0 < lo < hi < 0.5 * fs):
        return math.nan
    kt = tire_secant_stiffness_n_per_m(x2, tire) * tire.stiffness_exponent
    lm = linear_model(vehicle, kt, tire_damping_ns_per_m(x2, tire))
    ap, bp, cp, _, _ = cont2discrete((lm.A, lm.B1[:, None], lm.C_meas[:1],
                                      np.zeros((1, 1))), dt)
    af, bf, cf, df = zpk2ss(*butter(2, [lo, hi], btype="band", fs=fs, output="zpk"))
    n_p, n_f = ap.shape[0], af.shape[0]
    n = n_p + 2 * n_f           # plant, band-pass, band-pass
    a = np.zeros((n, n))
    b = np.zeros((n, 1))
    c = np.zeros((1, n))
    first = slice(n_p, n_p + n_f)
    second = slice(n_p + n_f, n)
    a[:n_p, :n_p] = ap
    b[:n_p] = bp
    a[first, :n_p] = bf @ cp
    a[first, first] = af
    a[second, :n_p] = bf @ df @ cp
    a[second, first] = bf @ cf
    a[second, second] = af
    c[:, :n_p] = df @ df @ cp
    c[:, first] = df @ cf
    c[:, second] = cf
    cov = scipy.linalg.solve_discrete_lyapunov(a, b @ b.T)
    step = max(1, int(fs // fit_rate_hz))
    a_step = np.linalg.matrix_power(a, step)
    lag1 = a_step @ cov
    c0 = float((c @ cov @ c.T)[0, 0])
    c1 = float((c @ lag1 @ c.T)[0, 0])
    c2 = float((c @ a_step @ lag1 @ c.T)[0, 0])
    a1, a2 = np.linalg.solve([[c0, c1], [c1, c0]], [c1, c2])
    return float(ar2_frequency_hz.py_func(float(a1), float(a2), dt * step, lo, hi))


def wheel_hop_tracker_parameters(cfg: RigConfig, *, band_hz: tuple[float, float] = (5.0, 20.0),
                                 fit_rate_hz: float = 200.0) -> FloatArray:
    """The runtime tracker's parameter array (layout ``WH_*``) for the loop of ``cfg``;
    all zeros (off) when the band does not fit below the loop's Nyquist frequency."""
    out = np.zeros(WH_SIZE)
    dt = cfg.sample_time_s
    fs = 1.0 / dt
    lo, hi = band_hz
    if not (0.0 < lo < hi < 0.5 * fs):
        return out
    sos = butter(2, [lo, hi], btype="band", fs=fs, output="sos")
    step = max(1, int(fs // fit_rate_hz))
    t_fit = dt * step
    impulse = np.zeros(round(5.0 / dt))
    impulse[0] = 1.0
    h = sosfilt(sos, sosfilt(sos, impulse))
    noise_ms = cfg.noise.rattlespace_std_m ** 2 * float(np.sum(h * h))
    lam = math.exp(-t_fit / TRACK_WINDOW_S)
    n_min = round(TRACK_MIN_DATA_S / t_fit)
    out[WH_ON] = 1.0
    out[WH_STEP] = step
    out[WH_LAMBDA] = lam
    out[WH_FDECAY] = math.exp(-dt / FORCE_RELEASE_S)
    out[WH_FMAX] = PASSIVE_FORCE_N
    out[WH_SETTLE] = round(TRACK_SETTLE_S / dt)
    out[WH_NMIN] = (1.0 - lam ** n_min) / (1.0 - lam)  # n_min samples in a row, weighted
    out[WH_RMIN] = TRACK_SNR ** 2 * noise_ms
    out[WH_TFIT] = t_fit
    out[WH_LO], out[WH_HI] = lo, hi
    out[WH_SOS:WH_SOS + 10] = np.concatenate([np.r_[sec[:3], sec[4:]] for sec in sos])
    scales = np.geomspace(*TIRE_SCALE_RANGE, TABLE_POINTS)
    freqs = [passive_wheel_hop_hz(layer_config(cfg, 1.0, tire_scale=float(k)),
                                  band_hz=band_hz, fit_rate_hz=fit_rate_hz) for k in scales]
    out[WH_TAB_F:WH_TAB_F + TABLE_POINTS] = np.log(freqs)
    out[WH_TAB_S:WH_TAB_S + TABLE_POINTS] = np.log(scales)
    return out


def tire_stiffness_scale(wheel_hop_hz: float, cfg: RigConfig, *,
                         dt_s: float | None = None) -> float:
    """The factor on ``cfg.tire.stiffness_coefficient`` [-] whose rig reads
    ``wheel_hop_hz`` [Hz] (a passive run's :func:`wheel_hop_frequency_hz`, sampled every
    ``dt_s``) by :func:`passive_wheel_hop_hz`, the rest of ``cfg`` as configured.  NaN
    for a non-finite frequency or one outside the predictions for
    :data:`TIRE_SCALE_RANGE`."""
    if not math.isfinite(wheel_hop_hz):
        return math.nan
    coeff = cfg.tire.stiffness_coefficient

    def miss(scale: float) -> float:
        tire = cfg.replace(tire={"stiffness_coefficient": coeff * scale})
        return passive_wheel_hop_hz(tire, dt_s=dt_s) - wheel_hop_hz

    lo, hi = TIRE_SCALE_RANGE
    m_lo, m_hi = miss(lo), miss(hi)
    if not (m_lo <= 0.0 <= m_hi):       # (NaN compares False)
        return math.nan
    return float(brentq(miss, lo, hi, xtol=1e-4))
