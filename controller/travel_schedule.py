"""Travel schedule: road-adaptive blending between a comfort law and a travel law
(docs/design.md §12).

Weight set 2 rides the body softly and uses the rattlespace for it; weight set 1 keeps
the travel and gives up comfort.  The schedule runs both LQ gains of each model on the
same estimate and blends their forces by how much travel the road is using now, in the
spirit of LPV gain scheduling on suspension deflection (Fialho and Balas 2002):

    usage  e_k = max(|r_k - c|, lambda e_{k-1})    (peak-hold envelope)
    share  beta = 1 - smoothstep((e - start) / (full - start))
    u = u_travel + beta (u_comfort - u_travel)

with r the LVDT reading, c the reading half-way between the stops
(``design.bump_stop_centre_lvdt_m``), lambda = exp(-T / ``schedule_release_s``).  The
envelope rises at once and falls slowly, so the law turns toward the travel set as soon
as the road asks for travel and stays there until the road has been quiet for about
``schedule_release_s``.  Both
gains are stabilising LQ gains of the same augmented plant; the blend moves slowly
against the closed-loop modes except on its rise (a change of gain, not of state).

``weight_set = 0`` selects the schedule; ``design.schedule_weight_sets`` names the
comfort and the travel set.  The comfort set selected alone runs, with
``design.govern_comfort_set``, under the *travel governor*: the same machinery with the
thresholds moved up to the stops (``design.governor_start_m`` / ``governor_full_m``), so
the comfort law is untouched until the reading nears a stop or the road preview
(``controller.road_preview``) predicts an excursion.  This is the plain-Python
statement of the law (tests); the runtime's numba kernel is
``controller.runtime.kernels.travel_comfort_share``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig

__all__ = ["SCHEDULE_SIZE", "THRESHOLDS", "Thresholds", "TravelSchedule", "comfort_share",
           "travel_schedule"]

#: length of :meth:`TravelSchedule.as_array` (the runtime's parameter slots)
SCHEDULE_SIZE = 4

#: which thresholds a schedule runs on: the reading's (``design.schedule_start_m`` /
#: ``schedule_full_m``), a live road preview's (``design.preview_schedule_*``) or the
#: travel governor's (``design.governor_*``); the runtime keeps one row per name, in
#: this order
Thresholds = Literal["reading", "preview", "governor"]
THRESHOLDS: tuple[Thresholds, ...] = ("reading", "preview", "governor")


@dataclass(frozen=True)
class TravelSchedule:
    """Parameters of the schedule (SI units); the runtime switches it on per weight set."""

    centre_m: float            # c, LVDT reading half-way between the stops
    start_m: float             # usage where the blend toward the travel law begins
    full_m: float              # usage at which the travel law has the whole force
    release_decay: float       # lambda, per-tick decay of the usage envelope

    def as_array(self) -> FloatArray:
        return np.array([self.centre_m, self.start_m, 1.0 / (self.full_m - self.start_m),
                         self.release_decay])


def travel_schedule(cfg: RigConfig, thresholds: Thresholds = "reading") -> TravelSchedule:
    """The schedule of ``cfg`` (``design.schedule_*``, ``design.bump_stop_centre_lvdt_m``)
    on ``thresholds`` (:data:`THRESHOLDS`): ``"reading"`` the reading-driven one,
    ``"preview"`` the one that runs while a road preview is live, ``"governor"`` the
    travel governor's, which runs the comfort set alone until near the stops (preview
    live or not).  ValueError for another name."""
    d = cfg.design
    tau = d.schedule_release_s
    decay = math.exp(-cfg.sample_time_s / tau) if tau > 0.0 else 0.0
    if thresholds == "governor":
        start, full = d.governor_start_m, d.governor_full_m
    elif thresholds == "preview":
        start, full = d.preview_schedule_start_m, d.preview_schedule_full_m
    elif thresholds == "reading":
        start, full = d.schedule_start_m, d.schedule_full_m
    else:
        raise ValueError(f"schedule thresholds {thresholds!r}: allowed {list(THRESHOLDS)}")
    return TravelSchedule(centre_m=d.bump_stop_centre_lvdt_m, start_m=start, full_m=full,
                          release_decay=decay)


def comfort_share(envelope_m: float, schedule: TravelSchedule) -> float:
    """beta in [0, 1]: the comfort law's share of the force at usage ``envelope_m`` [m]."""
    x = (envelope_m - schedule.start_m) / (schedule.full_m - schedule.start_m)
    x = min(max(x, 0.0), 1.0)
    return 1.0 - x * x * (3.0 - 2.0 * x)
