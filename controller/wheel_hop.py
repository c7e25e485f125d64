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
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.signal import butter, sosfiltfilt

from controller.arrays import FloatArray

__all__ = ["MIN_FIT_S", "wheel_hop_frequency_hz"]

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
    p = np.roots([1.0, -a1, -a2])[0]            # one of the pair (conjugates: same angle)
    if p.imag == 0.0 or not abs(p) < 1.0:       # not a damped oscillation
        return math.nan
    f = abs(math.atan2(p.imag, p.real)) / (2.0 * math.pi * dt_s * step)
    return f if lo <= f <= hi else math.nan
