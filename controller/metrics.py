"""Ride and suspension metrics of a simulated run.

* ``absorbed_power``: mean square of the sprung acceleration filtered by the thesis's
  human-body filter F(s) = 12 s / (s^2 + 30.02 s + 901.3) (Eq. 2.2) [(m/s^2)^2 units of
  the filter output].
* ``wk_rms``: ISO 2631-1 frequency-weighted RMS acceleration with the Wk weighting
  (vertical, seated), built from the standard's transfer-function definition
  (Annex A): band limiting (0.4 Hz high-pass, 100 Hz low-pass, Butterworth Q = 1/sqrt 2),
  acceleration-velocity transition (f3 = f4 = 12.5 Hz, Q4 = 0.63) and upward step
  (f5 = 2.37 Hz, Q5 = 0.91, f6 = 3.35 Hz, Q6 = 0.91).
* accelerations, rattlespace (about static), dynamic tire load / static load, time off
  the ground, actuator force, hydraulic power.

Continuous filters are discretised with the bilinear transform at the trace's sample
rate and applied with ``scipy.signal.sosfilt`` from rest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import signal

from controller.arrays import FloatArray

__all__ = [
    "WK_TABLE",
    "compute_metrics",
    "filter_signal",
    "human_filter_tf",
    "wk_tf",
]


#: ISO 2631-1 Table 3, Wk weighting factors (x 1000 in the standard) at centre frequencies.
WK_TABLE: dict[float, float] = {
    0.5: 0.418, 1.0: 0.482, 2.0: 0.531, 4.0: 0.967, 5.0: 1.039, 6.3: 1.054, 8.0: 1.036,
    10.0: 0.988, 16.0: 0.768, 20.0: 0.636, 31.5: 0.405, 50.0: 0.246,
}


def human_filter_tf(num: Sequence[float] = (12.0, 0.0),
                    den: Sequence[float] = (1.0, 30.02, 901.3)) -> tuple[FloatArray, FloatArray]:
    """(num, den) of the thesis's F(s) in descending powers of s."""
    return np.asarray(num, dtype=float), np.asarray(den, dtype=float)


def wk_tf() -> tuple[FloatArray, FloatArray]:
    """(num, den) of ISO 2631-1 Wk = H_h H_l H_t H_s in descending powers of s."""
    w = {k: 2.0 * math.pi * f for k, f in
         {"1": 0.4, "2": 100.0, "3": 12.5, "4": 12.5, "5": 2.37, "6": 3.35}.items()}
    q1 = q2 = 1.0 / math.sqrt(2.0)
    q4, q5, q6 = 0.63, 0.91, 0.91
    h_num = [1.0, 0.0, 0.0]
    h_den = [1.0, w["1"] / q1, w["1"] ** 2]
    l_num = [w["2"] ** 2]
    l_den = [1.0, w["2"] / q2, w["2"] ** 2]
    # H_t = (1 + s/w3) / (1 + s/(Q4 w4) + s^2/w4^2), scaled to monic denominator
    t_num = [w["4"] ** 2 / w["3"], w["4"] ** 2]
    t_den = [1.0, w["4"] / q4, w["4"] ** 2]
    # H_s = (s^2 + s w5/Q5 + w5^2) / (s^2 + s w6/Q6 + w6^2)   (gain 1 at high frequency)
    s_num = [1.0, w["5"] / q5, w["5"] ** 2]
    s_den = [1.0, w["6"] / q6, w["6"] ** 2]
    num = np.polymul(np.polymul(h_num, l_num), np.polymul(t_num, s_num))
    den = np.polymul(np.polymul(h_den, l_den), np.polymul(t_den, s_den))
    return num, den


def filter_signal(x: FloatArray, num: FloatArray, den: FloatArray, dt_s: float) -> FloatArray:
    """Apply the continuous filter num/den to samples ``x`` (bilinear transform, from rest)."""
    z, p, k = signal.tf2zpk(num, den)
    zd, pd, kd = signal.bilinear_zpk(z, p, k, fs=1.0 / dt_s)
    sos = signal.zpk2sos(zd, pd, kd)
    return np.asarray(signal.sosfilt(sos, np.asarray(x, dtype=float)), dtype=float)


def _rms(x: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else math.nan


def compute_metrics(dt_s: float, accel_mps2: FloatArray, rattlespace_m: FloatArray,
                    tire_force_n: FloatArray, static_tire_load_n: float,
                    force_n: FloatArray, hydraulic_power_w: FloatArray,
                    off_ground_s: FloatArray, bump_stop_s: FloatArray | None = None,
                    settle_s: float = 0.0,
                    human_filter: tuple[Sequence[float], Sequence[float]] | None = None,
                    ) -> dict[str, float]:
    """Metrics of one run from per-tick traces (true signals, SI).

    ``rattlespace_m`` is about the static position.  ``off_ground_s`` / ``bump_stop_s``
    hold the time spent off the ground / on a bump stop during each tick.  Filters run
    over the whole trace; statistics skip the first ``settle_s`` seconds.
    """
    n = accel_mps2.shape[0]
    i0 = min(round(settle_s / dt_s), max(n - 1, 0))
    num, den = human_filter_tf(*(human_filter or ((12.0, 0.0), (1.0, 30.02, 901.3))))
    acc_f = filter_signal(accel_mps2, num, den, dt_s)
    wn, wd = wk_tf()
    acc_wk = filter_signal(accel_mps2, wn, wd, dt_s)
    a, r = accel_mps2[i0:], rattlespace_m[i0:]
    dyn_tire = tire_force_n[i0:] - static_tire_load_n
    duration = (n - i0) * dt_s
    off = float(np.sum(off_ground_s[i0:]))
    bump = float(np.sum(bump_stop_s[i0:])) if bump_stop_s is not None else 0.0
    finite = bool(np.all(np.isfinite(a)) and np.all(np.isfinite(r)))
    return {
        "accel_rms_mps2": _rms(a),
        "accel_peak_mps2": float(np.max(np.abs(a))) if a.size else math.nan,
        "absorbed_power": float(np.mean(np.square(acc_f[i0:]))),
        "wk_rms_mps2": _rms(acc_wk[i0:]),
        "rattlespace_rms_m": _rms(r),
        "rattlespace_peak_m": float(np.max(np.abs(r))) if r.size else math.nan,
        "tire_load_rms_ratio": _rms(dyn_tire) / static_tire_load_n,
        "time_off_ground_s": off,
        "time_off_ground_fraction": off / duration if duration > 0 else 0.0,
        "bump_stop_time_s": bump,
        "force_rms_n": _rms(force_n[i0:]),
        "hydraulic_power_mean_w": float(np.mean(hydraulic_power_w[i0:])),
        "hydraulic_power_peak_w": float(np.max(np.abs(hydraulic_power_w[i0:]))),
        "finite": float(finite),
    }
