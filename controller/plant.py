"""Quarter-car plant laws and the family of linear models (thesis Ch. I, NOTES.md).

States (positions measured from the *unloaded* springs, so gravity acts):

    x1 = w - zs     body position below the road reference        [m]
    x2 = w - zu     tire deflection, compression positive         [m]
    x3 = zs'        body velocity (up positive)                   [m/s]
    x4 = zu'        wheel velocity (up positive)                  [m/s]

Rattlespace (suspension compression, the LVDT reading) is x1 - x2 = zu - zs.
Input u is the actuator force [N] (pushes the body up and the wheel down); the
disturbance is the road velocity w' [m/s].

Free-body diagram (this fixes the thesis's sign typo in the last row of Eq. 1.4/1.9):

    M zs'' =  K (x1 - x2) + C (x4 - x3) + u - M g
    m zu'' = -K (x1 - x2) - C (x4 - x3) - u + f_tire - m g
    f_tire = f_k(x2) + Ct(x2) x2'        (only for x2 > 0, never pulling)

Each linear model j uses the secant stiffness Kt_j = f_k(x2j)/x2j and Ct_j = Ct(x2j),
and is affine: x' = A_j x + B2 u + B1_j w' + G g with G = [0, 0, -1, -1].  Gravity is
handled explicitly by working in deviations from the model's own passive static
equilibrium xbar_j (A_j xbar_j + G g = 0), where it cancels; the airborne model
(Kt = Ct = 0) has no equilibrium and keeps gravity as a known input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig, TireConfig, VehicleConfig

__all__ = [
    "GRAVITY_INPUT",
    "LinearModel",
    "linear_model",
    "model_family",
    "static_equilibrium",
    "static_tire_deflection_m",
    "tire_damping_ns_per_m",
    "tire_force_n",
    "tire_secant_stiffness_n_per_m",
]


#: Column multiplying g in x' = A x + B2 u + B1 w' + G g.
GRAVITY_INPUT: FloatArray = np.array([0.0, 0.0, -1.0, -1.0])


def tire_force_n(x2_m: float, tire: TireConfig) -> float:
    """Tire stiffness force f_k = k' (1000 x2)^e  [N]; zero when off the ground (x2 <= 0)."""
    if x2_m <= 0.0:
        return 0.0
    return float(tire.stiffness_coefficient * (1000.0 * x2_m) ** tire.stiffness_exponent)


def tire_damping_ns_per_m(x2_m: float, tire: TireConfig) -> float:
    """Tire damping coefficient Ct(x2) [Ns/m] (Eq. 1.2, Ns/mm -> Ns/m), held above saturation."""
    if x2_m <= 0.0:
        return 0.0
    mm = min(1000.0 * x2_m, tire.damping_saturation_mm)
    return float(1000.0 * (tire.damping_c2 * mm**2 + tire.damping_c3 * mm**3))


def tire_secant_stiffness_n_per_m(x2_m: float, tire: TireConfig) -> float:
    """Kt(x2) = f_k(x2) / x2 [N/m] (the thesis's instantaneous stiffness)."""
    if x2_m <= 0.0:
        return 0.0
    return tire_force_n(x2_m, tire) / x2_m


def static_tire_deflection_m(cfg: RigConfig) -> float:
    """Static tire deflection of the nonlinear plant: f_k(x2) = (M + m) g (closed form)."""
    v, t = cfg.vehicle, cfg.tire
    load = (v.sprung_mass_kg + v.unsprung_mass_kg) * v.gravity_mps2
    return float((load / t.stiffness_coefficient) ** (1.0 / t.stiffness_exponent) / 1000.0)


def static_equilibrium(cfg: RigConfig) -> FloatArray:
    """Passive static equilibrium of the nonlinear plant, state [x1, x2, 0, 0] [m, m, m/s, m/s]."""
    v = cfg.vehicle
    x2 = static_tire_deflection_m(cfg)
    rattle = v.sprung_mass_kg * v.gravity_mps2 / v.suspension_stiffness_n_per_m
    return np.array([x2 + rattle, x2, 0.0, 0.0])


@dataclass(frozen=True)
class LinearModel:
    """One linear model of the family (continuous time, SI).

    Shapes: A (4, 4), B2 (4,), B1 (4,), C_meas (2, 4) with D_meas (2,) so that the
    measurement [rattlespace, sprung acceleration] = C_meas x + D_meas u (+ the gravity
    term -g on the acceleration row in absolute coordinates, which vanishes in deviations).
    ``equilibrium`` is xbar (4,) or None for the airborne model.
    """

    name: str
    deflection_m: float
    tire_stiffness_n_per_m: float
    tire_damping_ns_per_m: float
    airborne: bool
    A: FloatArray
    B2: FloatArray
    B1: FloatArray
    C_meas: FloatArray
    D_meas: FloatArray
    equilibrium: FloatArray | None


def linear_model(vehicle: VehicleConfig, kt: float, ct: float, *, name: str = "",
                 deflection_m: float = 0.0) -> LinearModel:
    """The linear model with tire stiffness ``kt`` [N/m] and damping ``ct`` [Ns/m]."""
    M, m = vehicle.sprung_mass_kg, vehicle.unsprung_mass_kg
    K, C = vehicle.suspension_stiffness_n_per_m, vehicle.suspension_damping_ns_per_m
    g = vehicle.gravity_mps2
    A = np.array([
        [0.0, 0.0, -1.0, 0.0],
        [0.0, 0.0, 0.0, -1.0],
        [K / M, -K / M, -C / M, C / M],
        [-K / m, (K + kt) / m, C / m, -(C + ct) / m],
    ])
    B2 = np.array([0.0, 0.0, 1.0 / M, -1.0 / m])
    B1 = np.array([1.0, 1.0, 0.0, ct / m])
    C_meas = np.vstack([np.array([1.0, -1.0, 0.0, 0.0]), A[2]])
    D_meas = np.array([0.0, 1.0 / M])
    airborne = kt == 0.0
    if airborne:
        eq = None
    else:
        x2 = (M + m) * g / kt
        eq = np.array([x2 + M * g / K, x2, 0.0, 0.0])
    return LinearModel(name or f"kt{kt:.0f}_ct{ct:.0f}", deflection_m, kt, ct, airborne,
                       A, B2, B1, C_meas, D_meas, eq)


def model_family(cfg: RigConfig) -> list[LinearModel]:
    """The bank's models: every linearisation deflection x every tire-damping scale, in
    configuration order (deflection major), then the airborne model if configured."""
    models: list[LinearModel] = []
    for x2j in cfg.design.linearisation_deflections_m:
        kt = tire_secant_stiffness_n_per_m(x2j, cfg.tire)
        ct0 = tire_damping_ns_per_m(x2j, cfg.tire)
        for scale in cfg.design.tire_damping_scales:
            suffix = "" if len(cfg.design.tire_damping_scales) == 1 else f"_ct{scale:g}"
            models.append(linear_model(cfg.vehicle, kt, ct0 * scale,
                                       name=f"x2_{1000 * x2j:g}mm{suffix}", deflection_m=x2j))
    if cfg.design.include_airborne_model:
        models.append(linear_model(cfg.vehicle, 0.0, 0.0, name="airborne", deflection_m=0.0))
    return models
