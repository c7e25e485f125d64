"""End-stop barrier: a control-barrier-function safety filter on the force reference
(docs/design.md §9.7).

The end-stop guard (:mod:`controller.stop_guard`) fades a force toward a stop only in
the last ``stop_guard_m`` before it, too late for the body's momentum.  The barrier
looks at the braking distance instead.  Per stop, in that stop's own frame (d the
distance to the stop [m], v the approach rate [m/s], u the actuator force toward the
stop [N], p the passive suspension force toward it, -(K r + C v) for the compression
stop, r the LVDT reading from static):

    h = d - margin - v+^2 / (2 a) - lag v+          a = braking_force / M

is the distance left once the actuator, after its reaction time ``lag``, has braked the
body (mass M, the wheel held by the tire) at ``braking_force``.  v is the LVDT rate
low-passed at the body mode (``stop_barrier_rate_lowpass_hz``): the body's momentum,
not the wheel hop's, whose few millimetres are the margin's.  The barrier condition
dh/dt >= -gamma h (Ames et al.) with  M dv/dt = u + p  gives the largest admissible
force toward the stop

    u <= M (gamma h - v+) / (lag + v+ / a) - p        (and >= -braking_force)

with p the worst case over K, C within ``passive_uncertainty`` d of nominal: (1 - d) p
when the spring and damper push away from the stop, (1 + d) p when toward it

(for v <= 0 the bound at v = 0+: continuous in v; with h >= 0 it only tightens the
condition).  h >= 0 is then forward invariant for the design model: the rattlespace
stays ``margin`` short of the stop.  The bound never asks for more than the braking
force away from the stop (below that h < 0 already).  The filter is a clip of the
law's force F (F > 0 extends the suspension) to [-u_hi, u_lo]: it changes F only when
F would violate a barrier, and then by the least amount; if the two bounds cross (both
stops near), the nearer stop's (smaller h) wins.

This is the plain-Python statement of the law (tests); the runtime's numba kernel is
``controller.runtime.kernels.stop_barrier``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig

__all__ = ["BARRIER_SIZE", "StopBarrier", "barrier_force", "braking_force_n",
           "force_bound_toward_stop", "stop_barrier"]

#: length of :meth:`StopBarrier.as_array` (the runtime's parameter slots)
BARRIER_SIZE = 9


@dataclass(frozen=True)
class StopBarrier:
    """Parameters of the barrier (SI units); ``mass_kg`` = 0: barrier off."""

    mass_kg: float                  # M, the body whose momentum is braked
    stiffness_n_per_m: float        # K, suspension spring (force away from a stop)
    damping_ns_per_m: float         # C, suspension damper
    margin_m: float                 # distance short of each stop kept free
    braking_force_n: float          # actuator force the braking distance counts on
    lag_s: float                    # reaction time of the force loop
    rate_per_s: float               # gamma of dh/dt >= -gamma h
    rate_filter_coeff: float        # per-tick coefficient of the low-pass on the LVDT rate
    passive_uncertainty: float      # d: K, C known within [1 - d, 1 + d] x nominal

    @property
    def decel_mps2(self) -> float:
        """a, the braking deceleration of the body [m/s^2]."""
        return self.braking_force_n / self.mass_kg

    def as_array(self) -> FloatArray:
        return np.array([self.mass_kg, self.stiffness_n_per_m, self.damping_ns_per_m,
                         self.margin_m, self.braking_force_n, self.lag_s, self.rate_per_s,
                         self.rate_filter_coeff, self.passive_uncertainty])


def braking_force_n(cfg: RigConfig, stall_force_n: float, force_limit_n: float) -> float:
    """The actuator force a braking law counts on [N]: ``design.stop_barrier_force_fraction``
    of the stall force A Ps ``stall_force_n`` (the valve loses force when the piston
    moves), at most the force loop's ``force_limit_n``.  The barrier's and the stop
    clamp's (``design.preview_clamp_brake``)."""
    return cfg.design.stop_barrier_force_fraction * min(stall_force_n, force_limit_n)


def stop_barrier(cfg: RigConfig, stall_force_n: float, force_limit_n: float) -> StopBarrier:
    """The barrier of ``cfg`` (``design.stop_barrier*``, the vehicle's M, K, C) for an
    actuator of stall force A Ps ``stall_force_n`` behind a force loop clipping the
    reference at ``force_limit_n``; all zeros when ``design.stop_barrier`` is off."""
    d, v = cfg.design, cfg.vehicle
    if not d.stop_barrier:
        return StopBarrier(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    braking = braking_force_n(cfg, stall_force_n, force_limit_n)
    corner = 2.0 * math.pi * d.stop_barrier_rate_lowpass_hz     # [rad/s]
    coeff = 1.0 - math.exp(-corner * cfg.sample_time_s)
    return StopBarrier(mass_kg=v.sprung_mass_kg, stiffness_n_per_m=v.suspension_stiffness_n_per_m,
                       damping_ns_per_m=v.suspension_damping_ns_per_m,
                       margin_m=d.stop_barrier_margin_m, braking_force_n=braking,
                       lag_s=d.stop_barrier_lag_s, rate_per_s=d.stop_barrier_rate_per_s,
                       rate_filter_coeff=coeff,
                       passive_uncertainty=d.stop_barrier_passive_uncertainty)


def force_bound_toward_stop(distance_m: float, approach_rate_mps: float,
                            passive_toward_n: float, b: StopBarrier) -> tuple[float, float]:
    """(largest admissible actuator force toward a stop [N], barrier h [m]) at distance
    ``distance_m`` from it, approaching at ``approach_rate_mps`` (negative: moving
    away), the passive suspension pushing toward it with ``passive_toward_n``."""
    vp = max(approach_rate_mps, 0.0)
    a = b.decel_mps2
    d = b.passive_uncertainty        # worst case: least help, most push
    passive_toward_n *= (1.0 + d) if passive_toward_n > 0.0 else (1.0 - d)
    h = distance_m - b.margin_m - vp * vp / (2.0 * a) - b.lag_s * vp
    bound = b.mass_kg * (b.rate_per_s * h - vp) / (b.lag_s + vp / a) - passive_toward_n
    return max(bound, -b.braking_force_n), h


def barrier_force(force_n: float, rattlespace_m: float, rattlespace_rate_mps: float,
                  rebound_stop_m: float, compression_stop_m: float, b: StopBarrier) -> float:
    """The force [N] (> 0 extends) after the barrier, for the law's ``force_n`` at the LVDT
    reading ``rattlespace_m`` (compression positive, static 0) moving at
    ``rattlespace_rate_mps``; the stops engage at ``rebound_stop_m`` / ``compression_stop_m``."""
    if b.mass_kg <= 0.0:
        return force_n
    passive = b.stiffness_n_per_m * rattlespace_m + b.damping_ns_per_m * rattlespace_rate_mps
    u_hi, h_hi = force_bound_toward_stop(compression_stop_m - rattlespace_m,
                                         rattlespace_rate_mps, -passive, b)
    u_lo, h_lo = force_bound_toward_stop(rattlespace_m - rebound_stop_m,
                                         -rattlespace_rate_mps, passive, b)
    f_min, f_max = -u_hi, u_lo
    if f_min > f_max:                   # the bounds cross: the nearer stop wins
        return f_min if h_hi <= h_lo else f_max
    return min(max(force_n, f_min), f_max)
