"""Sprung-mass estimator (issue 22, docs/design.md §10): least squares with exponential
forgetting on the measured body equation of the quarter car.

The body's equation, in the LVDT frame about the static position (z compression +,
a = zs'' with gravity removed, F the actuator force from the load cell, F_bs the bump-stop
force the bank computes from the LVDT reading):

    M a = F + F_bs + K z + C z'

K and C are the configured spring and damper (they do not change with ballast); M is what
the ballast changes.  A ballast change also shifts the static position (a constant
-ΔM g on the right until the LVDT is re-zeroed), and the accelerometer and load cell
carry offsets: all three are constants, so both sides go through the same band-pass
(2nd-order Butterworth high-pass, then 2nd-order low-pass; the same LTI filter on both
sides keeps the equation exact) before the fit.  With φ = BP(a) and y = BP(F + F_bs +
K z + C z'), z' the backward difference of the LVDT reading,

    S_φφ <- λ S_φφ + φ²,   S_φy <- λ S_φy + φ y,   M̂ = S_φy / S_φφ

(scalar recursive least squares with forgetting factor λ = exp(-T / window)).  The
estimate updates only while S_φφ exceeds (window / T) x ``min_accel²``, the information
of a band-passed acceleration of that RMS over one window: on a quiet rig it holds.  It
is clamped to [0.25, 4] x the configured mass (the range of ``[emulator]
sprung_mass_scale``).  After a reset the filters start as if the rig were at rest; the fit
takes data only after :data:`SETTLE_TIME_CONSTANTS` time constants of the high-pass (1.8 s
at 0.5 Hz), so a start on a moving rig does not enter it as a transient.

:func:`mass_estimator_parameters` gives the kernel's parameter array
(``controller.runtime.kernels.mass_estimate``, slots ``F_ME*``); :class:`MassEstimator`
is the same recursion in plain Python (the reference the kernel is tested against).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from controller.arrays import FloatArray
from controller.config import RigConfig

__all__ = ["ME_SIZE", "ME_STATE_SIZE", "MassEstimator", "mass_estimator_parameters"]

#: clamp of the estimate, relative to the configured mass
RELATIVE_RANGE = (0.25, 4.0)
# parameter layout
(ME_M0, ME_K, ME_C, ME_INV_DT, ME_LAMBDA, ME_SMIN, ME_LO,
 ME_HI, ME_SETTLE) = range(9)
ME_HP = 9        # high-pass b0, b1, b2, a1, a2
ME_LP = 14       # low-pass b0, b1, b2, a1, a2
ME_SIZE = 19
# state layout
(ME_ZPREV, ME_HPA, ME_LPA, ME_HPY, ME_LPY, ME_SAA, ME_SAY, ME_EST,
 ME_NUPD, ME_NSEEN) = (0, 1, 3, 5, 7, 9, 10, 11, 12, 13)
ME_STATE_SIZE = 14
#: after a reset the band-pass settles this many time constants of its high-pass before
#: the fit takes data (the filters start as if the rig were at rest; it may be moving)
SETTLE_TIME_CONSTANTS = 4.0


def _biquad(kind: str, corner_hz: float, fs_hz: float) -> FloatArray:
    b, a = signal.butter(2, corner_hz, btype=kind, fs=fs_hz)
    b, a = b / a[0], a / a[0]
    return np.array([b[0], b[1], b[2], a[1], a[2]])


def mass_estimator_parameters(cfg: RigConfig) -> FloatArray:
    """The kernel's parameters from ``[design] mass_estimator_*``; only the configured
    mass when the estimator is off (``mass_estimator_window_s`` = 0: λ = 0)."""
    p = np.zeros(ME_SIZE)
    d, v = cfg.design, cfg.vehicle
    p[ME_M0] = v.sprung_mass_kg
    if d.mass_estimator_window_s <= 0.0:
        return p
    dt = cfg.sample_time_s
    fs = d.sample_rate_hz
    p[ME_K] = v.suspension_stiffness_n_per_m
    p[ME_C] = v.suspension_damping_ns_per_m
    p[ME_INV_DT] = 1.0 / dt
    p[ME_LAMBDA] = math.exp(-dt / d.mass_estimator_window_s)
    p[ME_SMIN] = d.mass_estimator_min_accel_mps2 ** 2 / (1.0 - p[ME_LAMBDA])
    p[ME_LO] = RELATIVE_RANGE[0] * v.sprung_mass_kg
    p[ME_HI] = RELATIVE_RANGE[1] * v.sprung_mass_kg
    lo, hi = d.mass_estimator_band_hz
    # decay time constant of the 2nd-order Butterworth high-pass: 1 / (ζ ω) = √2 / (2π lo)
    p[ME_SETTLE] = math.ceil(SETTLE_TIME_CONSTANTS * math.sqrt(2.0) / (2.0 * math.pi * lo)
                             / dt)
    p[ME_HP:ME_HP + 5] = _biquad("highpass", lo, fs)
    p[ME_LP:ME_LP + 5] = _biquad("lowpass", hi, fs)
    return p


class MassEstimator:
    """The estimator in plain Python (one sample at a time; the kernel's reference)."""

    def __init__(self, params: FloatArray) -> None:
        self.p = np.asarray(params, dtype=float)
        self.reset()

    def reset(self) -> None:
        self.z_prev = math.nan
        self.s_hp_a = np.zeros(2)
        self.s_lp_a = np.zeros(2)
        self.s_hp_y = np.zeros(2)
        self.s_lp_y = np.zeros(2)
        self.s_aa = 0.0
        self.s_ay = 0.0
        self.estimate_kg = float(self.p[ME_M0])
        self.updates = 0
        self.seen = 0

    @staticmethod
    def _df2t(c: FloatArray, s: FloatArray, x: float) -> float:
        y = c[0] * x + s[0]
        s[0] = c[1] * x - c[3] * y + s[1]
        s[1] = c[2] * x - c[4] * y
        return float(y)

    def step(self, force_n: float, rattlespace_m: float, accel_mps2: float) -> float:
        """One sample: actuator + bump-stop force [N], LVDT reading [m], acceleration
        [m/s^2]; returns the estimate [kg]."""
        p = self.p
        if not p[ME_LAMBDA] > 0.0:          # off
            return self.estimate_kg
        hp, lp = p[ME_HP:ME_HP + 5], p[ME_LP:ME_LP + 5]
        if math.isnan(self.z_prev):         # first sample: the high-passes at steady state
            self.z_prev = rattlespace_m
            y0 = force_n + p[ME_K] * rattlespace_m
            for s, x in ((self.s_hp_a, accel_mps2), (self.s_hp_y, y0)):
                s[0] = (hp[1] + hp[2]) * x
                s[1] = hp[2] * x
        zdot = (rattlespace_m - self.z_prev) * p[ME_INV_DT]
        self.z_prev = rattlespace_m
        y = force_n + p[ME_K] * rattlespace_m + p[ME_C] * zdot
        phi = self._df2t(lp, self.s_lp_a, self._df2t(hp, self.s_hp_a, accel_mps2))
        yb = self._df2t(lp, self.s_lp_y, self._df2t(hp, self.s_hp_y, y))
        if self.seen < p[ME_SETTLE]:
            self.seen += 1
            return self.estimate_kg
        lam = p[ME_LAMBDA]
        self.s_aa = lam * self.s_aa + phi * phi
        self.s_ay = lam * self.s_ay + phi * yb
        if self.s_aa > p[ME_SMIN]:
            self.estimate_kg = min(max(self.s_ay / self.s_aa, p[ME_LO]), p[ME_HI])
            self.updates += 1
        return self.estimate_kg
