"""Servo-hydraulic actuator of the emulated rig (Alleyne & Hedrick 1995 form).

The actuator sits between body and wheel.  Its load pressure P [Pa] acts on the piston
area A [m^2]; the force u = A P pushes the body up and the wheel down (the convention of
``controller/plant.py``).  The servo valve spool x_v is normalised to [-1, 1]; the real
spool opening is ``spool_stroke_m * x_v``.

    x_v' = (i - x_v) / tau                                   (spool, first order)
    P'   = -beta P - alpha A (zs' - zu')
           + gamma x_s sgn(Ps - sgn(x_s) P) sqrt(|Ps - sgn(x_s) P|),   x_s = stroke * x_v

With the plant states zs' - zu' = x3 - x4.  |P| is held within the supply pressure Ps
(relief valves).  With the bypass valve open (the safe state) the two chambers are
shorted: P decays with ``bypass_time_constant_s`` whatever the spool and the piston do,
so the suspension is passive.  Loss of supply sets Ps = 0 (the valve can then only bleed
pressure to tank).

Sizing (defaults of ``controller.config.ActuatorConfig``): A = 1e-3 m^2 gives
A Ps = 10.3 kN at Ps = 10.3425 MPa, about twice the 5.5 kN static body weight of the
500 kg quarter car, and gamma = 1.545e9 x (1e-3 / 3.35e-4) = 4.6e9 keeps the no-load
velocity capability of Alleyne & Hedrick's actuator (gamma x_s sqrt(Ps) / (alpha A)).

Every function here is a numba kernel (no Python objects) used by ``hil.sim.plant``.
"""

from __future__ import annotations

import math

from numba import njit

from controller.config import ActuatorConfig

__all__ = [
    "hydraulic_power_w",
    "load_pressure_rate",
    "max_force_n",
    "no_load_velocity_mps",
]



@njit(cache=True)
def valve_flow_term(spool_m: float, p_pa: float, ps_pa: float, gamma: float) -> float:
    """gamma x_s sgn(Ps - sgn(x_s) P) sqrt(|Ps - sgn(x_s) P|)  [Pa/s]."""
    if spool_m == 0.0:
        return 0.0
    s = 1.0 if spool_m > 0.0 else -1.0
    dp = ps_pa - s * p_pa
    if dp >= 0.0:
        return gamma * spool_m * math.sqrt(dp)
    return -gamma * spool_m * math.sqrt(-dp)


@njit(cache=True)
def load_pressure_rate(p_pa: float, spool_m: float, rel_velocity_mps: float,
                       area_m2: float, ps_pa: float, alpha: float, beta: float,
                       gamma: float, bypass_open: bool, bypass_tau_s: float) -> float:
    """P' [Pa/s].  ``rel_velocity_mps`` = zs' - zu' (actuator extension rate)."""
    if bypass_open:
        return -p_pa / bypass_tau_s
    return (-beta * p_pa - alpha * area_m2 * rel_velocity_mps
            + valve_flow_term(spool_m, p_pa, ps_pa, gamma))


@njit(cache=True)
def hydraulic_power_w(p_pa: float, spool_m: float, ps_pa: float, gamma: float,
                      alpha: float, area_m2: float, bypass_open: bool) -> float:
    """Hydraulic power delivered by the valve to the actuator, P x Q_valve [W].

    In A&H's form P' = alpha (Q - A v) - beta P with alpha = 4 beta_e / Vt, so the valve
    flow is Q = (valve term) / alpha [m^3/s].  Zero with the bypass open.
    """
    if bypass_open:
        return 0.0
    q = valve_flow_term(spool_m, p_pa, ps_pa, gamma) / alpha
    return p_pa * q


def max_force_n(act: ActuatorConfig) -> float:
    """Stall force A Ps [N]."""
    return act.piston_area_m2 * act.supply_pressure_pa


def no_load_velocity_mps(act: ActuatorConfig) -> float:
    """Extension velocity at full spool and zero load: gamma x_s sqrt(Ps) / (alpha A)."""
    return (act.valve_gamma * act.spool_stroke_m * math.sqrt(act.supply_pressure_pa)
            / (act.alpha_n_per_m5 * act.piston_area_m2))
