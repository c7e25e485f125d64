"""Ride-height monitor: the body's mean position in its travel (issue 22, docs/design.md §9.9).

The bank's laws are designed for a body that sits at the stops' centre, 80 mm from either
stop.  Ballast put on without re-setting the spring preload (or re-zeroing the LVDT after
re-setting it) moves the static position by ΔM g / K toward one stop: +30 % ballast on the
default rig is 54 mm of sag, 26 mm of compression travel left.  The rattlespace-bias state
of the filters takes the sag up (§9.2), so the estimate does not show it, and every law,
passive too, then rides the stop.  This monitor says so.

The ride height is the mean LVDT reading about the stops' centre c
(``design.bump_stop_centre_lvdt_m``; compression positive), an exponential mean

    h_k = h_{k-1} + α (r_k - c - h_{k-1}),   α = 1 - exp(-T / τ)

with τ = ``safety.ride_height_window_s`` (2 s: the 1.2 Hz body mode leaves about ±1 mm of
ripple on ±20 mm of motion).  The body is *off centre* (StepFlag.RIDE_HEIGHT, a read-out,
no fault and no change of the law) once |h| exceeds ``safety.ride_height_warn_m`` and
until it falls below :data:`CLEAR_RATIO` times that; the travel left on the loaded side is
the travel less |h|.  h starts at 0 (the centre) after a reset, so one reading taken in
mid-stroke raises nothing; a body that really sits 54 mm off centre is found after
τ ln(54 / 34) ≈ 0.9 s.

This module holds the settings and the plain-Python statement (tests); the runtime's numba
kernel is ``controller.runtime.kernels.ride_height``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.config import RigConfig

__all__ = ["CLEAR_RATIO", "RideHeightSettings", "ride_height_settings", "ride_height_update"]

#: an off-centre body counts as centred again below this fraction of the warning level
CLEAR_RATIO = 0.75


@dataclass(frozen=True)
class RideHeightSettings:
    alpha: float                # α, weight of a new reading per tick
    centre_m: float             # c, LVDT reading half-way between the stops [m]
    warn_m: float               # off centre above this |h| [m] (0: never)
    clear_m: float              # centred again below this |h| [m]


def ride_height_settings(cfg: RigConfig, dt_s: float) -> RideHeightSettings:
    """The monitor's levels for ``cfg`` at the sample time ``dt_s`` (module docstring)."""
    sa = cfg.safety
    return RideHeightSettings(
        alpha=1.0 - math.exp(-dt_s / sa.ride_height_window_s),
        centre_m=cfg.design.bump_stop_centre_lvdt_m,
        warn_m=sa.ride_height_warn_m, clear_m=CLEAR_RATIO * sa.ride_height_warn_m)


def ride_height_update(height_m: float, off_centre: bool, rattlespace_m: float,
                       s: RideHeightSettings) -> tuple[float, bool]:
    """(h_k, off centre after this tick) from h_{k-1} = ``height_m`` (0 after a reset),
    the previous state ``off_centre`` and this tick's LVDT reading (a non-finite one
    changes nothing)."""
    x = rattlespace_m - s.centre_m
    if not math.isfinite(x):
        return height_m, off_centre
    h = height_m + s.alpha * (x - height_m)
    if s.warn_m <= 0.0:
        return h, False
    if off_centre:
        return h, abs(h) >= s.clear_m
    return h, abs(h) > s.warn_m
