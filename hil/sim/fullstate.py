"""Full-state LQ controller: the bank's LQ gain fed with the *true* plant state.

The ideal upper bound of the LQG design (no estimation error, no model blending): the
gain of the on-ground model nearest the static tire deflection (the single-LQG model),
applied to the true deviation of the nonlinear plant from its own static equilibrium and
to the human-filter states driven by the true sprung acceleration::

    u_k   = -K_w,j [x_k - x̄; x_f,k] - Ka_w,j [x̂_v; F; w; s_pending]
    x_f,k+1 = Ad x_f,k + Bd zs''_k           (same timing as the bank's runtime)

x = [x1, x2, x3, x4] of ``RigPlant.state``.  Everything else is exactly what the bank's
runtime does, so full-state LQ vs single LQG isolates the estimation error: x_f is driven
by the *measured* acceleration, and when the design carries an actuator part
(``design.actuator_gain``, ``design.actuator_model = "hydraulic"``) the law feeds back the
runtime's spool model x̂_v, the measured force F, the state w of the force loop's rate
filter (flow feedforward, run on the measured rattlespace) and the D spool commands still
on their way to the valve (``design.servo_model``, as ``tests/support/reference_bank.py``), and
the force goes through the bank's end-stop guard (``controller/stop_guard.py``).

The force still goes through the PI force loop and the servo-hydraulics, so it shares
the actuator's limits with the other controllers.  It reads the plant, so it exists only
in simulation (``hil.sim.closed_loop.run_closed_loop``).
"""

from __future__ import annotations

import math

import numpy as np

from controller.actuator import FlowFeedforward
from controller.arrays import FloatArray
from controller.artifact import Design
from controller.config import RigConfig
from controller.stop_guard import stop_guard_scale
from hil.sim.plant import RigPlant
from hil.sim.sensors import SensorReading

__all__ = ["FullStateLQ"]


class FullStateLQ:
    """LQ state feedback on the true state (study interface: reset / step / fault)."""

    name = "fullstate"

    def __init__(self, design: Design, cfg: RigConfig, weight_set: int = 1,
                 model: int | None = None) -> None:
        from controller.runtime.bank import default_single_model
        if not 1 <= weight_set <= design.n_weight_sets:
            raise ValueError(f"weight_set {weight_set}: allowed 1..{design.n_weight_sets}")
        j = default_single_model(design, cfg) if model is None else int(model)
        if not 0 <= j < design.n_models or bool(design.airborne[j]):
            raise ValueError(f"model {model!r}: must be an on-ground model index")
        self.model = j
        gain = np.asarray(design.lq_gain[weight_set - 1, j], dtype=float)
        self.kx: FloatArray = gain[:4].copy()
        self.kf: FloatArray = gain[4:6].copy()
        self.ad: FloatArray = np.asarray(design.human_filter_Ad, dtype=float).copy()
        self.bd: FloatArray = np.asarray(design.human_filter_Bd, dtype=float).copy()
        self.xf: FloatArray = np.zeros(2)
        act = getattr(design, "actuator_gain", None)
        servo = getattr(design, "servo_model", None)
        self.ka: FloatArray | None = None
        self.servo: tuple[float, float, float] = (0.0, 0.0, 1.0)
        self.spool_decay = 0.0
        self.xv = 0.0
        self.rate_state = math.nan
        self.pending: list[float] = []
        self.ff: FlowFeedforward | None = None
        if act is not None and servo is not None:
            self.ka = np.asarray(act[weight_set - 1, j], dtype=float).copy()
            self.servo = (float(servo[1]), float(servo[2]), float(servo[3]))
            self.spool_decay = float(servo[0])
            self.n_pending = round(float(servo[4]))
            c, a, stall, floor = (float(v) for v in servo[5:9])
            self.ff = FlowFeedforward(c, a, float(design.dt_s), stall, floor)
        else:
            self.n_pending = 0
        self.stop_lo, self.stop_hi = (float(v) for v in design.bump_stop[1:3])
        self.guard_width = cfg.design.stop_guard_m
        self.guard_lead_s = cfg.design.stop_guard_lead_s
        self.guard_deadband_mps = cfg.design.stop_guard_lead_deadband_mps
        self._xbar: FloatArray | None = None
        self._plant_id = -1
        self._fault = False
        self.reset()

    def reset(self) -> None:
        self.xf[:] = 0.0
        self.pending = [0.0] * self.n_pending
        self.xv = 0.0
        self.rate_state = math.nan
        self._xbar = None
        self._plant_id = -1
        self._fault = False

    @property
    def fault(self) -> bool:
        return self._fault

    def force(self, x: FloatArray, xbar: FloatArray, accel_mps2: float,
              force_n: float = 0.0, rattlespace_m: float = 0.0) -> float:
        """One tick from a state ``x`` (4,), its equilibrium ``xbar``, the measured zs''
        and (actuator part only) the measured actuator force and LVDT rattlespace; never
        raises."""
        if self.ff is not None and math.isnan(self.rate_state):
            self.rate_state = self.ff.initial_state(rattlespace_m)
        u = -float(self.kx @ (x - xbar)) - float(self.kf @ self.xf)
        if self.ka is not None:
            u -= float(self.ka @ np.array([self.xv, force_n, self.rate_state, *self.pending]))
        rate = (self.ff.rate_mps(self.rate_state, rattlespace_m) if self.ff is not None
                else 0.0)
        u *= stop_guard_scale(u, rattlespace_m, self.stop_lo, self.stop_hi, self.guard_width,
                              rate, self.guard_lead_s, self.guard_deadband_mps)
        if not (math.isfinite(u) and math.isfinite(accel_mps2) and math.isfinite(force_n)):
            self._fault = True
            return 0.0
        self.xf[:] = self.ad @ self.xf + self.bd * accel_mps2
        if self.ka is not None and self.ff is not None:
            kp, flim, olim = self.servo
            s_ff, self.rate_state = self.ff.step(self.rate_state, rattlespace_m, force_n)
            s = min(max(kp * (min(max(u, -flim), flim) - force_n) + s_ff, -olim), olim)
            self.pending.insert(0, s)
            applied = self.pending.pop()
            self.xv = self.spool_decay * self.xv + (1.0 - self.spool_decay) * applied
        return u

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        if self._xbar is None or self._plant_id != id(plant):
            self._xbar = plant.equilibrium()
            self._plant_id = id(plant)
        return self.force(plant.state[:4], self._xbar, reading.accel_mps2, reading.force_n,
                          reading.rattlespace_m)
