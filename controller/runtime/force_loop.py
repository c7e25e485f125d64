"""PI force inner loop with valve flow feedforward: actuator force reference [N] and the
LVDT reading -> normalised servo-valve spool command.

    e      = sat(force_ref, +-force_limit_n) - force_meas          [N]
    s_ff   = flow feedforward of the extension rate (below)         [-]
    spool  = clip(kp e + ki I + s_ff, +-output_limit)               [-]
    I     += e dt   (conditional integration, see below)            [N s]

The flow feedforward (:class:`controller.actuator.FlowFeedforward`, Alleyne & Hedrick)
opens the valve by the amount that supplies the flow the moving piston displaces, so
the oil column stops acting as a stiff spring between body and wheel and the PI only
has to make the force: s_ff = c v / sqrt(max(1 - sgn(v) F / (A Ps), floor)), v the
extension rate from the differentiated, low-passed LVDT reading (rattlespace r =
zu - zs, v = -r').  Its filter starts at rest on the first reading after ``reset()``.

The integral uses backward Euler (the error of this tick is included before the output
is computed), so with ``I`` the value after the update ``spool = kp e + ki I + s_ff``.

Anti-windup is *conditional integration* (clamping): the integrator is not advanced on
a tick where the unclipped output is saturated and the error would drive it further
into saturation; in addition ``ki I`` is kept within ``+-output_limit`` so that the
integrator can never hold more authority than the valve has.  Together these bound the
integrator under saturation and give recovery without overshoot from wind-up.

A non-finite reference, force or rattlespace returns 0.0 (valve centred), sets
``flags = StepFlag.NONFINITE_INPUT`` and leaves the integrator and the filter untouched;
the step never raises.  ``reset()`` clears the integrator and the rate filter.

The step is one numba call (:func:`pi_force_step`) on a parameter and a state array;
``tests/support/reference_force_loop.py`` keeps the plain-Python statement it matches
to the bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba as nb
import numpy as np

from controller.actuator import FlowFeedforward, flow_feedforward
from controller.config import ForceLoopConfig, RigConfig
from controller.runtime.compiled import direct_call
from controller.runtime.kernels import StepFlag
from controller.runtime.layout import SlotValue

__all__ = ["PIForceLoop", "pi_force_step"]

# parameter slots of pi_force_step
_P_KP, _P_KI, _P_LIM, _P_LIMF, _P_DT, _P_FF, _P_B, _P_A, _P_C, _P_STALL, _P_FLOOR = range(11)
_P_SIZE = 11
# state slots: integral I [N s], rate filter state w (NaN: no reading yet), error [N],
# s_ff, saturated (0 / 1), flags (StepFlag bits)
_S_I, _S_W, _S_E, _S_FF, _S_SAT, _S_FLAGS = range(6)
_S_SIZE = 6
_NONFINITE_INPUT = float(StepFlag.NONFINITE_INPUT)


@nb.njit(cache=True, nogil=True, inline="always")
def _max(a: float, b: float) -> float:
    """Python's ``max(a, b)``: a unless b is larger."""
    return b if b > a else a


@nb.njit(cache=True, nogil=True, inline="always")
def _min(a: float, b: float) -> float:
    """Python's ``min(a, b)``: a unless b is smaller."""
    return b if b < a else a


@nb.njit(nb.float64(nb.float64[::1], nb.float64[::1], nb.float64, nb.float64, nb.float64),
         cache=True, nogil=True)
def pi_force_step(p: np.ndarray, s: np.ndarray, force_ref_n: float, force_meas_n: float,
                  rattlespace_m: float) -> float:
    """One tick of the force loop (module docstring) on the parameters ``p`` and the
    state ``s`` (:class:`PIForceLoop`'s slots): the spool command.  Allocation-free,
    never raises."""
    if not (math.isfinite(force_ref_n) and math.isfinite(force_meas_n)
            and math.isfinite(rattlespace_m)):
        s[_S_FLAGS] = _NONFINITE_INPUT
        return 0.0
    s[_S_FLAGS] = 0.0
    ff = 0.0
    if p[_P_FF] != 0.0:
        # FlowFeedforward.step: the rate filter (started at rest) and the sqrt law
        b = p[_P_B]
        w = s[_S_W]
        if math.isnan(w):
            w = -b * rattlespace_m
        rho = w + b * rattlespace_m
        s[_S_W] = (1.0 - p[_P_A]) * rho - b * rattlespace_m
        v = -rho
        c = p[_P_C]
        if v != 0.0 and c != 0.0:
            sgn = 1.0 if v > 0.0 else -1.0
            drop = _max(1.0 - sgn * force_meas_n / p[_P_STALL], p[_P_FLOOR])
            ff = c * v / math.sqrt(drop)
    s[_S_FF] = ff
    lim_f = p[_P_LIMF]
    ref = _min(_max(force_ref_n, -lim_f), lim_f)
    e = ref - force_meas_n
    s[_S_E] = e
    lim = p[_P_LIM]
    kp = p[_P_KP]
    ki = p[_P_KI]
    trial_i = s[_S_I] + e * p[_P_DT]
    unclipped = kp * e + ki * trial_i + ff
    winding_up = (unclipped > lim and e > 0.0) or (unclipped < -lim and e < 0.0)
    if not winding_up:
        s[_S_I] = trial_i
    if ki > 0.0:  # the integral term alone never exceeds the valve authority
        i_max = lim / ki
        s[_S_I] = _min(_max(s[_S_I], -i_max), i_max)
    out = kp * e + ki * s[_S_I] + ff
    s[_S_SAT] = 1.0 if abs(out) > lim else 0.0
    return _min(_max(out, -lim), lim)


class PIForceLoop:
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
        p = np.zeros(_P_SIZE)
        p[_P_KP], p[_P_KI] = self.kp_per_n, self.ki_per_ns
        p[_P_LIM], p[_P_LIMF], p[_P_DT] = self.output_limit, self.force_limit_n, self.dt_s
        if feedforward is not None:
            p[_P_FF] = 1.0
            p[_P_B] = feedforward.rate_input_gain_per_s
            p[_P_A] = feedforward.rate_filter_coeff
            p[_P_C] = feedforward.gain_s_per_m
            p[_P_STALL] = feedforward.stall_force_n
            p[_P_FLOOR] = feedforward.min_pressure_drop_fraction
        self._p = p
        self._s = np.zeros(_S_SIZE)
        self.reset()
        pi_force_step(p, self._s.copy(), 0.0, 0.0, 0.0)     # loaded now, not in a tick
        # without numba's per-call dispatch (controller/runtime/compiled.py): the two
        # arrays are this object's own, checked here, and never replaced
        self._call: Callable[..., float] = direct_call(pi_force_step,
                                                       (p, self._s, 0.0, 0.0, 0.0))

    @classmethod
    def from_config(cls, cfg: RigConfig) -> PIForceLoop:
        """The rig's force loop: ``cfg.force_loop`` at the controller rate with the flow
        feedforward of ``cfg`` (:func:`controller.actuator.flow_feedforward`)."""
        return cls(cfg.force_loop, cfg.sample_time_s, flow_feedforward(cfg))

    def reset(self) -> None:
        """Clear the integrator, the rate filter and the flags."""
        self._s[:] = 0.0
        self._s[_S_W] = math.nan

    def step(self, force_ref_n: float, force_meas_n: float, rattlespace_m: float) -> float:
        """One tick: the spool command in [-output_limit, output_limit]."""
        # Python floats take the entry point, any other input the dispatcher
        # (controller/runtime/compiled.py)
        if (type(force_ref_n) is float and type(force_meas_n) is float
                and type(rattlespace_m) is float):
            return self._call(self._p, self._s, force_ref_n, force_meas_n, rattlespace_m)
        return pi_force_step(self._p, self._s, force_ref_n, force_meas_n, rattlespace_m)

    # ------------------------------------------------------------------ read-outs
    integral_ns = SlotValue("_s", _S_I, float, "I [N s].")
    rate_state_mps = SlotValue("_s", _S_W, float, "w of the rate filter; NaN = no reading yet.")
    error_n = SlotValue("_s", _S_E, float, "The force error of the last tick [N].")
    feedforward_spool = SlotValue("_s", _S_FF, float, "s_ff of the last tick.")
    saturated = SlotValue("_s", _S_SAT, bool, "The last output was clipped.")
    flags = SlotValue("_s", _S_FLAGS, lambda v: StepFlag(int(v)),
                      "NONFINITE_INPUT when the last tick's inputs were not finite.")
