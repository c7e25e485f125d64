"""Road process noise: white road velocity with ISO 8608 intensity (thesis Ch. III, Fig. 3.3).

An ISO 8608 road has the one-sided spatial displacement PSD Gd(n) = Gd(n0) (n/n0)^-2,
n0 = 0.1 cycle/m, Gd in m^3.  At speed V the road velocity w' = V dw/dx has the flat
one-sided temporal PSD (2 pi f)^2 Gd(f/V)/V = 4 pi^2 n0^2 Gd(n0) V, so as continuous
white noise E[w'(t) w'(t+tau)] = W delta(tau) its (two-sided) intensity is

    W = 2 pi^2 n0^2 Gd(n0) V      [m^2/s]

(derivation in docs/design.md).  The bank tabulates filter gains over speed x roughness;
the flat table index is s = i_speed * Nr + i_rough.
"""

from __future__ import annotations

import math

import numpy as np

from controller.config import NoiseConfig

__all__ = [
    "ISO_CLASS_GD",
    "N0_CYCLES_PER_M",
    "iso_class_gd",
    "nearest_noise_entry",
    "noise_table_entries",
    "noise_table_index",
    "road_velocity_intensity",
]

#: ISO 8608 reference spatial frequency [cycle/m].
N0_CYCLES_PER_M = 0.1

#: ISO 8608 class -> Gd(n0) [m^3] (geometric mean of the class).
ISO_CLASS_GD: dict[str, float] = {c: 16e-6 * 4.0**i for i, c in enumerate("ABCDEFGH")}


def iso_class_gd(road_class: str) -> float:
    """Gd(n0) [m^3] of an ISO 8608 class 'A'..'H' (case-insensitive)."""
    key = road_class.strip().upper()
    if key not in ISO_CLASS_GD:
        raise ValueError(f"ISO 8608 road class {road_class!r}: allowed A..H")
    return ISO_CLASS_GD[key]


def road_velocity_intensity(speed_mps: float, roughness_gd: float) -> float:
    """Two-sided intensity W [m^2/s] of the white road velocity at ``speed_mps`` [m/s]
    on a road of roughness Gd(n0) = ``roughness_gd`` [m^3]."""
    if not (speed_mps > 0.0 and math.isfinite(speed_mps)):
        raise ValueError(f"speed {speed_mps!r} m/s: must be a positive number")
    if not (roughness_gd > 0.0 and math.isfinite(roughness_gd)):
        raise ValueError(f"roughness Gd(n0) {roughness_gd!r} m^3: must be a positive number")
    return 2.0 * math.pi**2 * N0_CYCLES_PER_M**2 * roughness_gd * speed_mps


def noise_table_index(i_speed: int, i_rough: int, n_rough: int) -> int:
    """Flat index s = i_speed * Nr + i_rough."""
    return i_speed * n_rough + i_rough


def noise_table_entries(noise: NoiseConfig) -> list[tuple[float, float, float]]:
    """(speed [m/s], Gd(n0) [m^3], W [m^2/s]) for every table entry, in flat-index order."""
    return [(v, gd, road_velocity_intensity(v, gd))
            for v in noise.speeds_mps for gd in noise.road_roughness_gd]


def nearest_noise_entry(speeds_mps: np.ndarray, roughness_gd: np.ndarray,
                        speed_mps: float, gd: float) -> int:
    """Flat index of the nearest table entry: nearest speed (linear), nearest roughness
    (in log Gd, the natural ISO class spacing).  Out-of-range values take the edge entry."""
    if not (math.isfinite(speed_mps) and math.isfinite(gd) and gd > 0.0):
        raise ValueError(f"road (speed {speed_mps!r} m/s, Gd {gd!r} m^3) is not valid")
    i_s = int(np.argmin(np.abs(np.asarray(speeds_mps) - speed_mps)))
    i_r = int(np.argmin(np.abs(np.log(np.asarray(roughness_gd)) - math.log(gd))))
    return noise_table_index(i_s, i_r, int(np.asarray(roughness_gd).shape[0]))
