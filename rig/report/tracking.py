"""Why the applied force reference and the measured force differ while active.

The PI force loop drives a flow-control valve: the actuator force obeys (linearised,
``controller/actuator.py``)

    F' = kq x_v - k_h v_rel        kq = A gamma x_s sqrt(Ps),  k_h = alpha A^2,

with v_rel = zs' - zu' = -d(rattlespace_m)/dt (rattlespace is compression +).  Under the
proportional path x_v ~ kp e the tracking error e = F_ref - F is therefore

    e ~ (F' + k_h v_rel) / (kp kq),

largest where the suspension moves fast: the valve must keep the oil column up with the
suspension's velocity.  Below the force-loop corner f_c = kp kq / 2 pi, the error's
component along the rattlespace rate has the slope -k_h / (kp kq) [N s/m], a number of
the recorded configuration (not fitted here), reduced to (1 - g) of it by the valve flow
feedforward (``force_loop.flow_feedforward_gain`` = g, ``controller/actuator.py``), which
supplies the oil column's flow itself.  What remains below f_c is mostly the loop's own
lag: a first-order loop with corner f_c following the applied reference leaves
|j f/f_c / (1 + j f/f_c)|^2 of its spectrum as error (computed from the recorded
reference's spectrum, no fit).  Above f_c the error is the reference's own
content that the loop does not follow.  With fuzzy blending much of that is the
reference dropping to the fallback force (``fuzzy.no_fire_fallback``, 0 N for "passive")
on single ticks where no fuzzy rule fired: the analysis splits the reference's content
above f_c between ticks within :data:`NO_FIRE_REACH_S` of such a tick and the others.

:func:`force_tracking` returns these numbers and the series the report plots: spectra of
the applied reference, the measured force and the error, and the low-passed error
against the rattlespace rate, all over the ACTIVE ticks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from controller.actuator import servo_model
from controller.arrays import FloatArray
from rig.report.series import Phase, RunSeries

__all__ = ["MIN_ACTIVE_S", "NO_FIRE_REACH_S", "ForceTracking", "force_tracking"]

#: the longest active stretch must last this long for the analysis [s]
MIN_ACTIVE_S = 0.5
#: a tick this close to a no-rule-fired tick counts as "near" one [s]
NO_FIRE_REACH_S = 0.01
_WELCH_SEGMENT_S = 1.024


@dataclass
class ForceTracking:
    """Force-tracking analysis of the ACTIVE ticks (NaN / empty when there are none)."""

    active_s: float = 0.0
    corner_hz: float = math.nan                  # kp kq / 2 pi
    oil_column_ns_per_m: float = math.nan        # k_h / (kp kq), no feedforward
    feedforward_gain: float = math.nan           # force_loop.flow_feedforward_gain
    residual_slope_ns_per_m: float = math.nan    # (1 - g) k_h / (kp kq)
    lag_error_rms_below_n: float = math.nan      # first-order loop's error below corner
    delay_ticks: int = 0                         # design.compute_delay_ticks
    designed_for_actuator: bool = True           # design.actuator_model == "hydraulic"
    ref_rms_n: float = math.nan
    meas_rms_n: float = math.nan
    error_rms_n: float = math.nan
    error_rms_below_n: float = math.nan          # error content below corner_hz
    error_rms_above_n: float = math.nan          # ... and above
    ref_rms_above_n: float = math.nan            # reference content above corner_hz
    meas_rms_above_n: float = math.nan
    explained_below: float = math.nan            # share of low-passed error variance
                                                 # explained by -residual slope * rate
    fitted_slope_ns_per_m: float = math.nan      # least-squares slope, for comparison
    no_fire_share: float = math.nan              # active ticks with NO_RULE_FIRED
    near_no_fire_share: float = math.nan         # active ticks near one (NO_FIRE_REACH_S)
    ref_rms_above_near_no_fire_n: float = math.nan   # reference above corner_hz, near ...
    ref_rms_above_elsewhere_n: float = math.nan      # ... and elsewhere
    freq_hz: FloatArray = field(default_factory=lambda: np.zeros(0))
    psd_ref: FloatArray = field(default_factory=lambda: np.zeros(0))   # N²/Hz
    psd_meas: FloatArray = field(default_factory=lambda: np.zeros(0))
    psd_error: FloatArray = field(default_factory=lambda: np.zeros(0))
    rate_mps: FloatArray = field(default_factory=lambda: np.zeros(0))  # d/dt rattlespace_m
    error_low_n: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def ok(self) -> bool:
        return self.freq_hz.size > 0


def _welch(segments: list[tuple[int, int]], nper: int, fs: float,
           *series: FloatArray) -> tuple[FloatArray, list[FloatArray]]:
    """Welch PSDs over the segments, weighted by their number of samples."""
    acc: list[FloatArray] = [np.zeros(nper // 2 + 1) for _ in series]
    total = 0
    f = np.zeros(0)
    for a, b in segments:
        if b - a < nper:
            continue
        for k, x in enumerate(series):
            f, p = signal.welch(np.nan_to_num(x[a:b]), fs=fs, nperseg=nper)
            acc[k] += p * (b - a)
        total += b - a
    return f, [p / total for p in acc] if total else []


def _band_rms(f: FloatArray, p: FloatArray, lo: float, hi: float) -> float:
    m = (f >= lo) & (f < hi)
    return float(np.sqrt(np.sum(p[m]) * (f[1] - f[0]))) if f.size > 1 else math.nan


def _rms(x: FloatArray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def force_tracking(s: RunSeries) -> ForceTracking:
    """Analyse the force tracking of the ACTIVE ticks of ``s``."""
    cfg = s.cfg
    sm = servo_model(cfg)
    ft = ForceTracking()
    ft.corner_hz = sm.kp_per_n * sm.flow_gain_n_per_s / (2 * math.pi)
    ft.oil_column_ns_per_m = sm.hydraulic_stiffness_n_per_m / (
        sm.kp_per_n * sm.flow_gain_n_per_s)
    ft.feedforward_gain = cfg.force_loop.flow_feedforward_gain
    ft.delay_ticks = int(cfg.design.compute_delay_ticks)
    ft.residual_slope_ns_per_m = (1.0 - ft.feedforward_gain) * ft.oil_column_ns_per_m
    ft.designed_for_actuator = cfg.design.actuator_model == "hydraulic"
    active = s.phase == Phase.ACTIVE
    ft.active_s = float(active.sum() * s.dt_s)
    spans = [(g.start, g.stop) for g in s.segments if g.phase is Phase.ACTIVE]
    longest = max((b - a for a, b in spans), default=0)
    if longest * s.dt_s < MIN_ACTIVE_S:
        return ft
    ref = s.force_ref_applied_n
    meas = s.signals["force_meas_n"]
    err = ref - meas
    ft.ref_rms_n = float(np.sqrt(np.nanmean(ref[active] ** 2)))
    ft.meas_rms_n = float(np.sqrt(np.nanmean(meas[active] ** 2)))
    ft.error_rms_n = float(np.sqrt(np.nanmean(err[active] ** 2)))
    fs = 1.0 / s.dt_s
    nper = min(int(2 ** round(math.log2(_WELCH_SEGMENT_S * fs))), 2 ** int(math.log2(longest)))
    f, (p_ref, p_meas, p_err) = _welch(spans, nper, fs, ref, meas, err)
    fc = min(ft.corner_hz, 0.45 * fs)
    ft.freq_hz, ft.psd_ref, ft.psd_meas, ft.psd_error = f, p_ref, p_meas, p_err
    ft.error_rms_below_n = _band_rms(f, p_err, 0.0, fc)
    ft.error_rms_above_n = _band_rms(f, p_err, fc, np.inf)
    ft.ref_rms_above_n = _band_rms(f, p_ref, fc, np.inf)
    ft.meas_rms_above_n = _band_rms(f, p_meas, fc, np.inf)
    ratio = (f / ft.corner_hz) ** 2
    ft.lag_error_rms_below_n = _band_rms(f, p_ref * ratio / (1.0 + ratio), 0.0, fc)
    # where the reference's content above the corner sits: near no-rule-fired ticks or not
    hp = signal.sosfiltfilt(signal.butter(4, fc, "highpass", fs=fs, output="sos"),
                            np.nan_to_num(ref))
    if np.any(s.flags >= 0):
        nf = s.no_rule_fired
        reach = max(1, round(NO_FIRE_REACH_S * fs))
        near = np.convolve(nf.astype(np.int64), np.ones(2 * reach + 1, np.int64),
                           "same") > 0
        ft.no_fire_share = float(nf[active].mean())
        ft.near_no_fire_share = float(near[active].mean())
        ft.ref_rms_above_near_no_fire_n = _rms(hp[active & near])
        ft.ref_rms_above_elsewhere_n = _rms(hp[active & ~near])
    # low-passed error against the low-passed rattlespace rate (zero-phase, same filter)
    sos = signal.butter(2, fc, fs=fs, output="sos")
    rate = np.gradient(signal.sosfiltfilt(sos, np.nan_to_num(s.signals["rattlespace_m"])),
                       s.dt_s)
    err_low = signal.sosfiltfilt(sos, np.where(active, np.nan_to_num(err), 0.0))
    x, y = rate[active], err_low[active]
    ft.rate_mps, ft.error_low_n = x, y
    var = float(np.var(y))
    if var > 0.0:
        ft.explained_below = 1.0 - float(np.var(y + ft.residual_slope_ns_per_m * x)) / var
        xc = x - x.mean()
        denom = float(np.dot(xc, xc))
        ft.fitted_slope_ns_per_m = (-float(np.dot(xc, y - y.mean())) / denom
                                    if denom > 0 else math.nan)
    return ft
