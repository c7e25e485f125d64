"""Sprung-mass estimator (issue 22, docs/design.md §10): least squares with exponential
forgetting on the measured body equation of the quarter car.

The body's equation, in the LVDT frame about the static position (z compression +,
a = zs'' with gravity removed, F the actuator force from the load cell, F_bs the bump-stop
force the bank computes from the LVDT reading):

    F + F_bs = M a - K z - C z'

M is what the ballast changes; the spring rate K and damping C of a real rig are known
only roughly (a 25 % spread of C alone biased a fit of M with the configured K and C by
up to 56 %), so all three are fitted, K and C with a weak prior at the configured values.
A ballast change also shifts the static position (a constant -ΔM g on the right until
the LVDT is re-zeroed), and the accelerometer and load cell carry offsets: all constants,
so every signal goes through the same band-pass (2nd-order Butterworth high-pass, then
2nd-order low-pass; one LTI filter on every term keeps the equation exact) before the
fit.  z' is the backward difference of the LVDT reading, the velocity half a tick ago, so
a, z and F enter as the mean of this sample and the last (the same instant; with the
samples as they are, the half tick biased M by -7 % on the course: the wheel hop's
velocity is large).  With φ = [BP(a), -BP(z), -BP(z')] and y = BP(F + F_bs),

    R <- λ R + φ φᵀ,   b <- λ b + φ y,   (R + W) θ = b + W θ0,   θ = [M, K, C]

(recursive least squares with forgetting factor λ = exp(-T / window); W = diag(0, w_K,
w_C), θ0 the configured values).  The prior weighs like one window of data at the gate's
excitation: w_K = (window / T) (M0 a_min / K0)², w_C = (window / T) (M0 a_min / C0)²,
with a_min = ``min_accel``; on the course the data carry 30-100 x that.  The estimate
updates only while R_aa exceeds (window / T) x a_min², the information of a band-passed
acceleration of that RMS over one window: on a quiet rig it holds.  M is clamped to
[0.25, 4] x the configured mass (the range of ``[emulator] sprung_mass_scale``), K and C
to the same multiples of theirs.  After a reset the filters start as if the rig were at
rest; the fit takes data only after :data:`SETTLE_TIME_CONSTANTS` time constants of the
high-pass (1.8 s at 0.5 Hz), so a start on a moving rig does not enter it as a transient.

Near an isolated stop contact the fit takes no data: F_bs is the least known term (1 MN/m
on a geometry known to the calibration's millimetres; 3 mm off is 3 kN on every tick on
a stop, and the band-pass spreads one contact over a second).  While contacts are rare
(``contacts_rare``: the bank's stop-contact window within its budget) a reading within
:data:`STOP_BAND_M` of a stop's engagement holds the fit for :data:`HOLD_TIME_CONSTANTS`
time constants of the high-pass; the old data keep fading meanwhile.  When contacts are
frequent (a sagged rig living on a stop) they are all the data there is and the fit
takes them (docs/design.md §10).

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

__all__ = ["ME_SIZE", "ME_STATE_SIZE", "MassEstimator", "mass_estimator_parameters",
           "solve_body_fit"]

#: clamp of the estimate, relative to the configured mass
RELATIVE_RANGE = (0.25, 4.0)
# parameter layout
(ME_M0, ME_K, ME_C, ME_INV_DT, ME_LAMBDA, ME_SMIN, ME_LO,
 ME_HI, ME_SETTLE) = range(9)
ME_HP = 9        # high-pass b0, b1, b2, a1, a2
ME_LP = 14       # low-pass b0, b1, b2, a1, a2
ME_WK, ME_WC = 19, 20    # prior weights of K and C
ME_HOLD_TICKS = 21       # ticks the fit takes no data after an isolated stop contact
ME_STOP_LO, ME_STOP_HI = 22, 23   # ... a reading outside (LO, HI) [m]
ME_SIZE = 24
# state layout: band-pass states (2 floats each) of a, y, z, z'; the information matrix
# R (a, z, z' order; symmetric: 6 floats) and vector b; the estimates M, K, C
(ME_ZPREV, ME_HPA, ME_LPA, ME_HPY, ME_LPY, ME_SAA, ME_SAY, ME_EST,
 ME_NUPD, ME_NSEEN) = (0, 1, 3, 5, 7, 9, 10, 11, 12, 13)
ME_HPZ, ME_LPZ, ME_HPV, ME_LPV = 14, 16, 18, 20
ME_RAZ, ME_RAV, ME_RZZ, ME_RZV, ME_RVV, ME_BZ, ME_BV = range(22, 29)
ME_KEST, ME_CEST = 29, 30
ME_APREV, ME_FPREV = 31, 32      # the last sample's acceleration and force
ME_HOLD = 33                     # ticks the fit still holds
ME_STATE_SIZE = 34
#: after a reset the band-pass settles this many time constants of its high-pass before
#: the fit takes data (the filters start as if the rig were at rest; it may be moving)
SETTLE_TIME_CONSTANTS = 4.0
#: a reading this close to a stop's engagement [m] counts as a stop contact for the fit
STOP_BAND_M = 0.003
#: after an isolated stop contact the fit takes no data for this many time constants of
#: the high-pass
HOLD_TIME_CONSTANTS = 2.0


def _biquad(kind: str, corner_hz: float, fs_hz: float) -> FloatArray:
    b, a = signal.butter(2, corner_hz, btype=kind, fs=fs_hz)
    b, a = b / a[0], a / a[0]
    return np.array([b[0], b[1], b[2], a[1], a[2]])


def mass_estimator_parameters(cfg: RigConfig, stops_lvdt_m: tuple[float, float]
                              ) -> FloatArray:
    """The kernel's parameters from ``[design] mass_estimator_*``; ``stops_lvdt_m`` the
    LVDT readings [m] at which the rebound and compression stops engage (the design's
    ``bump_stop[1:]``); only the configured mass when the estimator is off
    (``mass_estimator_window_s`` = 0: λ = 0)."""
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
    hp_tau_ticks = math.sqrt(2.0) / (2.0 * math.pi * lo) / dt
    p[ME_SETTLE] = math.ceil(SETTLE_TIME_CONSTANTS * hp_tau_ticks)
    # near an isolated stop contact the fit takes no data for HOLD_TIME_CONSTANTS time
    # constants of the high-pass (the band-pass's memory of the contact)
    p[ME_HOLD_TICKS] = math.ceil(HOLD_TIME_CONSTANTS * hp_tau_ticks)
    stop_lo, stop_hi = stops_lvdt_m
    p[ME_STOP_LO] = stop_lo + STOP_BAND_M
    p[ME_STOP_HI] = stop_hi - STOP_BAND_M
    p[ME_HP:ME_HP + 5] = _biquad("highpass", lo, fs)
    p[ME_LP:ME_LP + 5] = _biquad("lowpass", hi, fs)
    # the prior on K and C: one window of data at the gate's excitation, the force
    # M0 a_min read as a spring or damper force
    f_min = v.sprung_mass_kg * d.mass_estimator_min_accel_mps2
    p[ME_WK] = (f_min / p[ME_K]) ** 2 / (1.0 - p[ME_LAMBDA])
    p[ME_WC] = (f_min / p[ME_C]) ** 2 / (1.0 - p[ME_LAMBDA])
    return p


def solve_body_fit(r: FloatArray, b: FloatArray) -> tuple[float, float, float]:
    """θ = [M, K, C] of the symmetric positive definite 3 x 3 system R θ = b (Cholesky;
    the kernel's arithmetic); NaN where R is not positive definite."""
    l00 = math.sqrt(r[0, 0]) if r[0, 0] > 0.0 else math.nan
    l10 = r[1, 0] / l00
    l20 = r[2, 0] / l00
    d1 = r[1, 1] - l10 * l10
    l11 = math.sqrt(d1) if d1 > 0.0 else math.nan
    l21 = (r[2, 1] - l20 * l10) / l11
    d2 = r[2, 2] - l20 * l20 - l21 * l21
    l22 = math.sqrt(d2) if d2 > 0.0 else math.nan
    y0 = b[0] / l00
    y1 = (b[1] - l10 * y0) / l11
    y2 = (b[2] - l20 * y0 - l21 * y1) / l22
    c = y2 / l22
    k = (y1 - l21 * c) / l11
    m = (y0 - l10 * k - l20 * c) / l00
    return m, k, c


class MassEstimator:
    """The estimator in plain Python (one sample at a time; the kernel's reference)."""

    def __init__(self, params: FloatArray) -> None:
        self.p = np.asarray(params, dtype=float)
        self.reset()

    def reset(self) -> None:
        self.z_prev = math.nan
        self.a_prev = 0.0
        self.f_prev = 0.0
        # band-pass states of a, y, z, z' (high-pass, low-pass)
        self.s_hp = np.zeros((4, 2))
        self.s_lp = np.zeros((4, 2))
        self.info = np.zeros((3, 3))
        self.vec = np.zeros(3)
        self.estimate_kg = float(self.p[ME_M0])
        self.spring_rate_n_per_m = float(self.p[ME_K])
        self.damping_ns_per_m = float(self.p[ME_C])
        self.updates = 0
        self.seen = 0
        self.hold = 0

    @staticmethod
    def _df2t(c: FloatArray, s: FloatArray, x: float) -> float:
        y = c[0] * x + s[0]
        s[0] = c[1] * x - c[3] * y + s[1]
        s[1] = c[2] * x - c[4] * y
        return float(y)

    def step(self, force_n: float, rattlespace_m: float, accel_mps2: float,
             contacts_rare: bool = True) -> float:
        """One sample: actuator + bump-stop force [N], LVDT reading [m], acceleration
        [m/s^2], whether stop contacts are rare (a contact then holds the fit); returns
        the estimate [kg]."""
        p = self.p
        if not p[ME_LAMBDA] > 0.0:          # off
            return self.estimate_kg
        hp, lp = p[ME_HP:ME_HP + 5], p[ME_LP:ME_LP + 5]
        if math.isnan(self.z_prev):         # first sample: the high-passes at steady state
            self.z_prev, self.a_prev, self.f_prev = rattlespace_m, accel_mps2, force_n
            for i, x in enumerate((accel_mps2, force_n, rattlespace_m, 0.0)):
                self.s_hp[i, 0] = (hp[1] + hp[2]) * x
                self.s_hp[i, 1] = hp[2] * x
        # the velocity half a tick ago, and the other signals at that instant
        zdot = (rattlespace_m - self.z_prev) * p[ME_INV_DT]
        mid = (0.5 * (accel_mps2 + self.a_prev), 0.5 * (force_n + self.f_prev),
               0.5 * (rattlespace_m + self.z_prev), zdot)
        self.z_prev, self.a_prev, self.f_prev = rattlespace_m, accel_mps2, force_n
        bp = [self._df2t(lp, self.s_lp[i], self._df2t(hp, self.s_hp[i], x))
              for i, x in enumerate(mid)]
        if contacts_rare and not p[ME_STOP_LO] < rattlespace_m < p[ME_STOP_HI]:
            self.hold = int(p[ME_HOLD_TICKS])
        if self.seen < p[ME_SETTLE]:
            self.seen += 1
            return self.estimate_kg
        weight = 1.0
        if self.hold > 0:                   # near an isolated contact: no data, old fades
            self.hold -= 1
            weight = 0.0
        phi = np.array([bp[0], -bp[2], -bp[3]])
        lam = p[ME_LAMBDA]
        self.info = lam * self.info + weight * np.outer(phi, phi)
        self.vec = lam * self.vec + weight * phi * bp[1]
        if self.info[0, 0] > p[ME_SMIN]:
            r = self.info + np.diag([0.0, p[ME_WK], p[ME_WC]])
            b = self.vec + np.array([0.0, p[ME_WK] * p[ME_K], p[ME_WC] * p[ME_C]])
            m, k, c = solve_body_fit(r, b)
            if math.isfinite(m) and math.isfinite(k) and math.isfinite(c):
                self.estimate_kg = min(max(m, p[ME_LO]), p[ME_HI])
                scale = p[ME_LO] / p[ME_M0], p[ME_HI] / p[ME_M0]
                self.spring_rate_n_per_m = min(max(k, scale[0] * p[ME_K]), scale[1] * p[ME_K])
                self.damping_ns_per_m = min(max(c, scale[0] * p[ME_C]), scale[1] * p[ME_C])
                self.updates += 1
        return self.estimate_kg
