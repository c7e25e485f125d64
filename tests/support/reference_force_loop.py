"""The force inner loop in plain Python, as it ran before its numba kernel
(``controller.runtime.force_loop.pi_force_step``): the reference the kernel must match
to the bit (tests/test_force_loop.py)."""

from __future__ import annotations

import math

from controller.actuator import FlowFeedforward
from controller.config import ForceLoopConfig
from controller.runtime.kernels import StepFlag

_NO_FLAGS = StepFlag(0)
_NONFINITE_INPUT = StepFlag.NONFINITE_INPUT


class ReferencePIForceLoop:
    """Discrete PI force controller with flow feedforward, reference saturation and
    anti-windup.  ``feedforward`` None runs the plain PI (``rattlespace_m`` unused)."""

    def __init__(self, cfg: ForceLoopConfig, dt_s: float,
                 feedforward: FlowFeedforward | None) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s = {dt_s!r}: must be a positive number of seconds")
        if feedforward is not None and not math.isclose(feedforward.dt_s, dt_s,
                                                        rel_tol=1e-12):
            raise ValueError(f"flow feedforward designed for dt {feedforward.dt_s!r} s, "
                             f"the force loop runs at {dt_s!r} s")
        self.kp_per_n = float(cfg.kp_per_n)
        self.ki_per_ns = float(cfg.ki_per_ns)
        self.output_limit = float(cfg.output_limit)
        self.force_limit_n = float(cfg.force_limit_n)
        self.dt_s = float(dt_s)
        self.feedforward = feedforward
        self.integral_ns = 0.0          # I [N s]
        self.flags = _NO_FLAGS
        self.saturated = False          # last output was clipped
        self.error_n = 0.0
        self.feedforward_spool = 0.0    # s_ff of the last tick
        self.rate_state_mps = math.nan  # w of the rate filter; NaN = no reading yet

    def reset(self) -> None:
        """Clear the integrator, the rate filter and the flags."""
        self.integral_ns = 0.0
        self.flags = _NO_FLAGS
        self.saturated = False
        self.error_n = 0.0
        self.feedforward_spool = 0.0
        self.rate_state_mps = math.nan

    def step(self, force_ref_n: float, force_meas_n: float, rattlespace_m: float) -> float:
        """One tick: the spool command in [-output_limit, output_limit]."""
        if not (math.isfinite(force_ref_n) and math.isfinite(force_meas_n)
                and math.isfinite(rattlespace_m)):
            self.flags = _NONFINITE_INPUT
            return 0.0
        self.flags = _NO_FLAGS
        ff = 0.0
        fwd = self.feedforward
        if fwd is not None:
            w = self.rate_state_mps
            if math.isnan(w):
                w = fwd.initial_state(rattlespace_m)
            ff, self.rate_state_mps = fwd.step(w, rattlespace_m, force_meas_n)
        self.feedforward_spool = ff
        lim_f = self.force_limit_n
        ref = min(max(force_ref_n, -lim_f), lim_f)
        e = ref - force_meas_n
        self.error_n = e
        lim = self.output_limit
        kp, ki = self.kp_per_n, self.ki_per_ns
        trial_i = self.integral_ns + e * self.dt_s
        unclipped = kp * e + ki * trial_i + ff
        winding_up = (unclipped > lim and e > 0.0) or (unclipped < -lim and e < 0.0)
        if not winding_up:
            self.integral_ns = trial_i
        if ki > 0.0:  # the integral term alone never exceeds the valve authority
            i_max = lim / ki
            self.integral_ns = min(max(self.integral_ns, -i_max), i_max)
        out = kp * e + ki * self.integral_ns + ff
        self.saturated = abs(out) > lim
        return min(max(out, -lim), lim)
