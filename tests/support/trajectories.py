"""Measurement trajectories of the piecewise-linear quarter car for the bank tests
(test_bank.py, test_monitor.py, test_estimator_robustness.py)."""

from __future__ import annotations

import math

import numpy as np

from controller.config import RigConfig, default_config
from controller.road_noise import road_velocity_intensity
from tests.support.reference_bank import quarter_car_measurements

SMOOTH_SPEED, SMOOTH_GD = 5.0, 16e-6       # ISO class A at 5 m/s: tight filters


def smooth_road_config(**design: object) -> RigConfig:
    """One noise-table entry (fast designs), tuned for a smooth road."""
    return default_config().replace(
        noise={"speeds_mps": [SMOOTH_SPEED], "road_roughness_gd": [SMOOTH_GD],
               "nominal_speed_mps": SMOOTH_SPEED, "nominal_roughness_gd": SMOOTH_GD},
        design=dict(design))


def trajectory(cfg: RigConfig, n: int, seed: int, *, drop_at: int | None = None,
               force_std: float = 300.0, deflection_m: float | None = None
               ) -> dict[str, np.ndarray]:
    """Measurements of the piecewise-linear quarter car on a road matching the filter
    tuning; ``drop_at``: the road falls 10 cm in 50 ms there (the wheel lifts off)."""
    rng = np.random.default_rng(seed)
    dt = cfg.sample_time_s
    w = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    road = rng.normal(0.0, math.sqrt(w / dt), n)
    if drop_at is not None:
        road[drop_at:drop_at + 50] -= 2.0
    force = rng.normal(0.0, force_std, n)
    return quarter_car_measurements(cfg, dt, road, force, rng, deflection_m=deflection_m)
