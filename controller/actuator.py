"""Linearised servo-hydraulic actuator under the PI force loop and the valve flow
feedforward: the design model of the force path (docs/design.md section 7).

The emulated rig's actuator (``hil/sim/hydraulics.py``, Alleyne & Hedrick form) linearised at
zero load pressure, force F = A P:

    x_v' = (s - x_v) / tau                          spool (normalised), s = spool command
    F'   = kq x_v - k_h (x3 - x4) - beta F          kq = A gamma x_s sqrt(Ps)   [N/s]
                                                    k_h = alpha A^2 (hydraulic stiffness)

Valve flow feedforward (:class:`FlowFeedforward`, Alleyne & Hedrick 1995).  The piston
displaces the flow A x_p' (x_p' = x3 - x4 = zs' - zu', the extension rate); with a closed
valve the oil column turns it into the force rate -alpha A^2 x_p', a 4.5e5 N/m spring in
parallel with the suspension that the PI can only fight by feedback.  The force loop
adds the spool that makes the valve supply that flow, gamma x_s sqrt(Ps - sgn(x_s) P) =
g alpha A x_p' (g = ``force_loop.flow_feedforward_gain``), in normalised units

    s_ff = c v / sqrt(max(1 - sgn(v) F / (A Ps), floor)),   c = g alpha A / (gamma x_s sqrt(Ps))

where v is the extension rate estimated from the LVDT (rattlespace r = zu - zs, so
v = -r'): the first-order low-pass (corner ``force_loop.rattle_rate_lowpass_hz``) of the
backward difference, a = 1 - e^{-2 pi f_c T}, b = a / T, in one state w [m/s]:

    rho_k = w_k + b r_k                 filtered r'  (= (1-a) rho_{k-1} + a (r_k - r_{k-1}) / T)
    w_k+1 = (1 - a) w_k - a b r_k
    v_k   = -rho_k

The sqrt term is the valve's pressure-drop law at the measured load pressure F / A: at
F = 3 kN (P = 0.29 Ps) the same spool passes 16 % less flow in the loaded direction.
``floor`` (``force_loop.min_pressure_drop_fraction``) bounds the correction where the
drop across the metering edge vanishes (near stall).  The design linearises at F = 0
(correction 1); the runtime applies it.

The PI force loop (``controller/runtime/force_loop.py``) runs in the controller; its proportional
path s_k = kp (fref_k - F_k) + s_ff,k is part of the design model, its integral (corner
ki / kp a decade below the crossover) is left out.  The spool command reaches the valve
``delay_ticks`` ticks later and is held over the tick (ZOH).

The runtime cannot measure x_v, so it runs this spool model on its own commands
(:class:`ServoModel` holds what it needs): s_k = clip(kp (clip(fref_k) - F_k) + s_ff,k),
the command applied now is s_{k-D}, x̂_v <- e^{-T/tau} x̂_v + (1 - e^{-T/tau}) s_{k-D}.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig

__all__ = ["FLOW_FEEDFORWARD_FIELDS", "SERVO_MODEL_SIZE", "FlowFeedforward", "ServoModel",
           "flow_feedforward", "servo_model"]


#: entries of the artifact's ``servo_model`` row after the five of the spool model
FLOW_FEEDFORWARD_FIELDS = ("gain_s_per_m", "rate_filter_coeff", "stall_force_n",
                           "min_pressure_drop_fraction")
SERVO_MODEL_SIZE = 5 + len(FLOW_FEEDFORWARD_FIELDS)


@dataclass(frozen=True)
class FlowFeedforward:
    """Valve flow feedforward of the force loop (module docstring).

    ``gain_s_per_m`` = c [spool per m/s of extension rate at zero load; 0 = off],
    ``rate_filter_coeff`` = a (low-pass of the differentiated LVDT), ``dt_s`` = T,
    ``stall_force_n`` = A Ps, ``min_pressure_drop_fraction`` = floor."""

    gain_s_per_m: float
    rate_filter_coeff: float
    dt_s: float
    stall_force_n: float
    min_pressure_drop_fraction: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain_s_per_m) and self.gain_s_per_m >= 0.0):
            raise ValueError(f"gain_s_per_m = {self.gain_s_per_m!r}: must be >= 0")
        if not 0.0 < self.rate_filter_coeff <= 1.0:
            raise ValueError(f"rate_filter_coeff = {self.rate_filter_coeff!r}: allowed (0, 1]")
        if not (math.isfinite(self.dt_s) and self.dt_s > 0.0):
            raise ValueError(f"dt_s = {self.dt_s!r}: must be a positive number of seconds")
        if not (math.isfinite(self.stall_force_n) and self.stall_force_n > 0.0):
            raise ValueError(f"stall_force_n = {self.stall_force_n!r}: must be > 0")
        if not 0.0 < self.min_pressure_drop_fraction <= 1.0:
            raise ValueError(f"min_pressure_drop_fraction = "
                             f"{self.min_pressure_drop_fraction!r}: allowed (0, 1]")

    @property
    def rate_input_gain_per_s(self) -> float:
        """b = a / T [1/s]: weight of the current LVDT sample in the filtered rate."""
        return self.rate_filter_coeff / self.dt_s

    def initial_state(self, rattlespace_m: float) -> float:
        """w that makes the first filtered rate zero (as if the rig had been at rest)."""
        return -self.rate_input_gain_per_s * rattlespace_m

    def rate_mps(self, w: float, rattlespace_m: float) -> float:
        """The filtered rattlespace rate r' [m/s, compression positive] this tick, from the
        state ``w`` before :meth:`step` advances it and the reading r [m]."""
        return w + self.rate_input_gain_per_s * rattlespace_m

    def step(self, w: float, rattlespace_m: float, force_meas_n: float) -> tuple[float, float]:
        """(s_ff, next w) for LVDT reading r [m] and load-cell force F [N] (module
        docstring).  Plain Python; ``controller.runtime.kernels.servo_update`` is the numba twin."""
        b = self.rate_input_gain_per_s
        rho = self.rate_mps(w, rattlespace_m)
        w_next = (1.0 - self.rate_filter_coeff) * rho - b * rattlespace_m
        return self.spool(-rho, force_meas_n), w_next

    def spool(self, extension_rate_mps: float, force_meas_n: float) -> float:
        """s_ff for extension rate v [m/s] at load force F [N] (sqrt pressure-drop law)."""
        v = extension_rate_mps
        if v == 0.0 or self.gain_s_per_m == 0.0:
            return 0.0
        sgn = 1.0 if v > 0.0 else -1.0
        drop = max(1.0 - sgn * force_meas_n / self.stall_force_n,
                   self.min_pressure_drop_fraction)
        return self.gain_s_per_m * v / math.sqrt(drop)

    def as_array(self) -> FloatArray:
        """The feedforward part of the artifact's ``servo_model`` row
        (:data:`FLOW_FEEDFORWARD_FIELDS`)."""
        return np.array([self.gain_s_per_m, self.rate_filter_coeff, self.stall_force_n,
                         self.min_pressure_drop_fraction])


def flow_feedforward(cfg: RigConfig) -> FlowFeedforward:
    """The force loop's flow feedforward for ``cfg`` (``force_loop`` and ``actuator``)."""
    a, fl = cfg.actuator, cfg.force_loop
    dt = cfg.sample_time_s
    c = (fl.flow_feedforward_gain * a.alpha_n_per_m5 * a.piston_area_m2
         / (a.valve_gamma * a.spool_stroke_m * math.sqrt(a.supply_pressure_pa)))
    return FlowFeedforward(
        gain_s_per_m=c,
        rate_filter_coeff=1.0 - math.exp(-2.0 * math.pi * fl.rattle_rate_lowpass_hz * dt),
        dt_s=dt,
        stall_force_n=a.piston_area_m2 * a.supply_pressure_pa,
        min_pressure_drop_fraction=fl.min_pressure_drop_fraction,
    )


@dataclass(frozen=True)
class ServoModel:
    """Linearised actuator + PI proportional path + flow feedforward + compute delay."""

    flow_gain_n_per_s: float        # kq = A gamma x_s sqrt(Ps)
    hydraulic_stiffness_n_per_m: float   # k_h = alpha A^2
    spool_time_constant_s: float
    leakage_per_s: float            # beta
    kp_per_n: float
    force_limit_n: float
    output_limit: float
    delay_ticks: int
    dt_s: float
    feedforward: FlowFeedforward

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
        """The artifact's ``servo_model`` row (:data:`SERVO_MODEL_SIZE`): [spool_decay, kp,
        force_limit, output_limit, delay_ticks, *feedforward.as_array()]."""
        return np.array([self.spool_decay, self.kp_per_n, self.force_limit_n,
                         self.output_limit, float(self.delay_ticks),
                         *self.feedforward.as_array()])


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
        feedforward=flow_feedforward(cfg),
    )
