"""Stop-contact monitor: contact time over a window -> degrade / re-arm (docs/design.md §9.8).

Contact is an LVDT reading r beyond the reading where a bump stop engages, less a band
(``safety.stop_contact_band_m``, 0 by default: on the stop):

    contact_k = r_k > r_hi - band  or  r_k < r_lo + band

with r_lo / r_hi the rebound / compression stops (``design.bump_stop_centre_lvdt_m`` -/+
``vehicle.rattlespace_travel_m``, the same readings as the filters' bump-stop input).  The
contact time in the window is an exponentially weighted sum of the contact ticks,

    E_k = λ E_{k-1} + T contact_k,      λ = exp(-T / τ)      (T the tick, τ the window)

in seconds: an episode of d << τ adds d, contact older than τ fades by e per τ, and E
never exceeds T / (1 - λ) ≈ τ (contact on every tick).  Above ``stop_contact_budget_s``
the bank degrades (StepFlag.STOP_DEGRADED, when ``stop_contact_degrade``): its force
authority ramps to ``stop_contact_authority`` (0: the zero force reference, i.e. the
passive suspension behind the compensated actuator) at the estimator monitor's rate; it
re-arms after E stayed below ``stop_contact_rearm_level_s`` for ``stop_contact_rearm_s``
and the authority ramps back.  Not a fault.

A contact *episode* starts on a contact tick after at least :data:`EPISODE_GAP_S` without
contact (LVDT noise and the wheel hop make one hit chatter across the threshold); the
runtime counts episodes and flags the ticks inside one (StepFlag.STOP_CONTACT).

This module holds the settings and the plain-Python statement of the window arithmetic
(tests); the runtime's numba kernel is ``controller.runtime.kernels.stop_contact``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.config import RigConfig

__all__ = ["EPISODE_GAP_S", "StopContactSettings", "contact_time_update",
           "stop_contact_settings"]

#: an episode ends after this long without contact [s]
EPISODE_GAP_S = 0.05


@dataclass(frozen=True)
class StopContactSettings:
    decay: float                # λ, per tick
    tick_s: float               # T, the contact time one contact tick adds [s]
    band_m: float               # contact band in front of each stop [m]
    budget_s: float             # degrade when E exceeds this [s]
    rearm_level_s: float        # re-arm after E stays below this ...
    rearm_ticks: int            # ... for this many ticks
    degrade: bool               # False: report only
    authority: float            # force authority of the travel-conservative law
    episode_gap_ticks: int      # an episode ends after this many ticks without contact


def stop_contact_settings(cfg: RigConfig, dt_s: float) -> StopContactSettings:
    """The monitor's levels for ``cfg`` at the sample time ``dt_s`` (module docstring)."""
    sa = cfg.safety
    return StopContactSettings(
        decay=math.exp(-dt_s / sa.stop_contact_window_s), tick_s=dt_s,
        band_m=sa.stop_contact_band_m, budget_s=sa.stop_contact_budget_s,
        rearm_level_s=sa.stop_contact_rearm_level_s,
        rearm_ticks=max(1, math.ceil(sa.stop_contact_rearm_s / dt_s - 1e-9)),
        degrade=sa.stop_contact_degrade, authority=sa.stop_contact_authority,
        episode_gap_ticks=max(1, round(EPISODE_GAP_S / dt_s)))


def contact_time_update(contact_time_s: float, contact: bool, s: StopContactSettings) -> float:
    """E_k from E_{k-1} = ``contact_time_s`` and this tick's ``contact`` [s]."""
    return s.decay * contact_time_s + (s.tick_s if contact else 0.0)
