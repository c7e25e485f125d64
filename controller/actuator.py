"""Linearised servo-hydraulic actuator under the PI force loop: the design model of the
force path (docs/design.md section 7).

The emulated rig's actuator (``hil/hydraulics.py``, Alleyne & Hedrick form) linearised at
zero load pressure, force F = A P:

    x_v' = (s - x_v) / tau                          spool (normalised), s = spool command
    F'   = kq x_v - k_h (x3 - x4) - beta F          kq = A gamma x_s sqrt(Ps)   [N/s]
                                                    k_h = alpha A^2 (hydraulic stiffness)

The PI force loop (``controller/force_loop.py``) runs in the controller; its proportional
path s_k = kp (fref_k - F_k) is part of the design model, its integral (corner ki / kp a
decade below the crossover) is left out.  The spool command reaches the valve
``delay_ticks`` ticks later and is held over the tick (ZOH).

The runtime cannot measure x_v, so it runs this spool model on its own commands
(:class:`ServoModel` holds what it needs): s_k = clip(kp (clip(fref_k) - F_k)), the
command applied now is s_{k-D}, x̂_v <- e^{-T/tau} x̂_v + (1 - e^{-T/tau}) s_{k-D}.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig

__all__ = ["ServoModel", "servo_model"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ServoModel:
    """Linearised actuator + PI proportional path + compute delay."""

    flow_gain_n_per_s: float        # kq = A gamma x_s sqrt(Ps)
    hydraulic_stiffness_n_per_m: float   # k_h = alpha A^2
    spool_time_constant_s: float
    leakage_per_s: float            # beta
    kp_per_n: float
    force_limit_n: float
    output_limit: float
    delay_ticks: int
    dt_s: float

    @property
    def spool_decay(self) -> float:
        """e^{-T / tau}: exact ZOH step of the spool."""
        return math.exp(-self.dt_s / self.spool_time_constant_s)

    def continuous(self) -> tuple[FloatArray, FloatArray]:
        """(A_act (2, 6), b_s (2,)): [x_v', F'] = A_act [x3, x4, ..., x_v, F] -- rows act on
        [x1, x2, x3, x4, x_v, F]; b_s multiplies the spool command."""
        a = np.zeros((2, 6))
        a[0, 4] = -1.0 / self.spool_time_constant_s
        a[1, 2] = -self.hydraulic_stiffness_n_per_m
        a[1, 3] = self.hydraulic_stiffness_n_per_m
        a[1, 4] = self.flow_gain_n_per_s
        a[1, 5] = -self.leakage_per_s
        b = np.array([1.0 / self.spool_time_constant_s, 0.0])
        return a, b

    def as_array(self) -> FloatArray:
        """The artifact's ``servo_model`` row: [spool_decay, kp, force_limit, output_limit,
        delay_ticks]."""
        return np.array([self.spool_decay, self.kp_per_n, self.force_limit_n,
                         self.output_limit, float(self.delay_ticks)])


def servo_model(cfg: RigConfig) -> ServoModel:
    a = cfg.actuator
    kq = a.piston_area_m2 * a.valve_gamma * a.spool_stroke_m * math.sqrt(a.supply_pressure_pa)
    return ServoModel(
        flow_gain_n_per_s=kq,
        hydraulic_stiffness_n_per_m=a.alpha_n_per_m5 * a.piston_area_m2**2,
        spool_time_constant_s=a.spool_time_constant_s,
        leakage_per_s=a.leakage_beta_per_s,
        kp_per_n=cfg.force_loop.kp_per_n,
        force_limit_n=cfg.force_loop.force_limit_n,
        output_limit=cfg.force_loop.output_limit,
        delay_ticks=int(cfg.design.compute_delay_ticks),
        dt_s=cfg.sample_time_s,
    )
