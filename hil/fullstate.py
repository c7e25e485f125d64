"""Full-state LQ controller: the bank's LQ gain fed with the *true* plant state.

The ideal upper bound of the LQG design (no estimation error, no model blending): the
gain of the on-ground model nearest the static tire deflection (the single-LQG model),
applied to the true deviation of the nonlinear plant from its own static equilibrium and
to the human-filter states driven by the true sprung acceleration::

    u_k   = -K_w,j [x_k - x̄; x_f,k]          (x = [x1, x2, x3, x4] of ``RigPlant.state``)
    x_f,k+1 = Ad x_f,k + Bd zs''_k           (same timing as the bank's runtime)

The force still goes through the PI force loop and the servo-hydraulics, so it shares
the actuator's limits with the other controllers.  It reads the plant, so it exists only
in simulation (``hil.study.loop.run_closed_loop``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from controller.artifact import Design
from controller.config import RigConfig
from hil.plant import RigPlant
from hil.sensors import SensorReading

__all__ = ["FullStateLQ"]

FloatArray = NDArray[np.float64]


class FullStateLQ:
    """LQ state feedback on the true state (study interface: reset / step / fault)."""

    name = "fullstate"

    def __init__(self, design: Design, cfg: RigConfig, weight_set: int = 1,
                 model: int | None = None) -> None:
        from controller.bank import default_single_model
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
        self._xbar: FloatArray | None = None
        self._plant_id = -1
        self._fault = False

    def reset(self) -> None:
        self.xf[:] = 0.0
        self._xbar = None
        self._plant_id = -1
        self._fault = False

    @property
    def fault(self) -> bool:
        return self._fault

    def force(self, x: FloatArray, xbar: FloatArray, accel_mps2: float) -> float:
        """One tick from a state ``x`` (4,), its equilibrium ``xbar`` and zs''; never raises."""
        u = -float(self.kx @ (x - xbar)) - float(self.kf @ self.xf)
        if not (math.isfinite(u) and math.isfinite(accel_mps2)):
            self._fault = True
            return 0.0
        self.xf[:] = self.ad @ self.xf + self.bd * accel_mps2
        return u

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        if self._xbar is None or self._plant_id != id(plant):
            self._xbar = plant.equilibrium()
            self._plant_id = id(plant)
        return self.force(plant.state[:4], self._xbar, plant.sprung_accel_mps2)
