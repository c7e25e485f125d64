"""PI force inner loop: actuator force reference [N] -> normalised servo-valve spool command.

    e      = sat(force_ref, +-force_limit_n) - force_meas          [N]
    spool  = clip(kp e + ki I, +-output_limit)                     [-]
    I     += e dt   (conditional integration, see below)           [N s]

The integral uses backward Euler (the error of this tick is included before the output
is computed), so with ``I`` the value after the update ``spool = kp e + ki I``.

Anti-windup is *conditional integration* (clamping): the integrator is not advanced on
a tick where the unclipped output is saturated and the error would drive it further
into saturation; in addition ``ki I`` is kept within ``+-output_limit`` so that the
integrator can never hold more authority than the valve has.  Together these bound the
integrator under saturation and give recovery without overshoot from wind-up.

A non-finite reference or measurement returns 0.0 (valve centred), sets
``flags = StepFlag.NONFINITE_INPUT`` and leaves the integrator untouched; the step never
raises.  ``reset()`` clears the integrator.
"""

from __future__ import annotations

import math

from controller.config import ForceLoopConfig
from controller.kernels import StepFlag

__all__ = ["PIForceLoop"]

# built once: StepFlag(...) goes through the enum machinery (~1 us) on every call
_NO_FLAGS = StepFlag(0)
_NONFINITE_INPUT = StepFlag.NONFINITE_INPUT


class PIForceLoop:
    """Discrete PI force controller with reference saturation and anti-windup."""

    def __init__(self, cfg: ForceLoopConfig, dt_s: float) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s = {dt_s!r}: must be a positive number of seconds")
        self.kp_per_n = float(cfg.kp_per_n)
        self.ki_per_ns = float(cfg.ki_per_ns)
        self.output_limit = float(cfg.output_limit)
        self.force_limit_n = float(cfg.force_limit_n)
        self.dt_s = float(dt_s)
        self.integral_ns = 0.0          # I [N s]
        self.flags = _NO_FLAGS
        self.saturated = False          # last output was clipped
        self.error_n = 0.0

    def reset(self) -> None:
        """Clear the integrator and the flags."""
        self.integral_ns = 0.0
        self.flags = _NO_FLAGS
        self.saturated = False
        self.error_n = 0.0

    def step(self, force_ref_n: float, force_meas_n: float) -> float:
        """One tick: the spool command in [-output_limit, output_limit]."""
        if not (math.isfinite(force_ref_n) and math.isfinite(force_meas_n)):
            self.flags = _NONFINITE_INPUT
            return 0.0
        self.flags = _NO_FLAGS
        lim_f = self.force_limit_n
        ref = min(max(force_ref_n, -lim_f), lim_f)
        e = ref - force_meas_n
        self.error_n = e
        lim = self.output_limit
        kp, ki = self.kp_per_n, self.ki_per_ns
        trial_i = self.integral_ns + e * self.dt_s
        unclipped = kp * e + ki * trial_i
        winding_up = (unclipped > lim and e > 0.0) or (unclipped < -lim and e < 0.0)
        if not winding_up:
            self.integral_ns = trial_i
        if ki > 0.0:  # the integral term alone never exceeds the valve authority
            i_max = lim / ki
            self.integral_ns = min(max(self.integral_ns, -i_max), i_max)
        out = kp * e + ki * self.integral_ns
        self.saturated = abs(out) > lim
        return min(max(out, -lim), lim)
