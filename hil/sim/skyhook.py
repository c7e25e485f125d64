"""Classic skyhook (+ optional groundhook) active damper from the rig's own sensors.

    u = -c_sky zs' + c_ground zu' - k_cancel C r'   (u > 0 pushes the body up, the wheel down)

zs' is the measured sprung acceleration integrated by a leaky integrator (a first-order
high-pass at ``velocity_highpass_hz`` removes drift from accelerometer bias); the
rattlespace rate r' (r = zu - zs) is the LVDT reading differentiated and low-passed at
``rattle_rate_lowpass_hz`` (150 Hz, the corner of the force loop's flow feedforward;
at 40 Hz the lag cost the damper-cancel term about a tenth of the absorbed power);
zu' = zs' + r'.  The passive spring K and damper C stay in place, the actuator adds the
skyhook force through the same PI force loop (with its flow feedforward) as the LQG;
``damper_cancel`` = k_cancel in [0, 1] lets the actuator cancel that fraction of the
passive damper's force C r' (the textbook "ideal skyhook" replaces the damper: 1).

The gains are tuned by a small grid search on the rough course (``rig study`` runs it:
:data:`TUNING_GRID`, chosen by :func:`select_gains`: the lowest absorbed power among the
settings whose rattlespace RMS and dynamic tire load RMS stay within
:data:`TUNING_LIMITS` of passive).  :data:`DEFAULT_GAINS` is the result of that search
with the default configuration (docs/study.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from controller.config import RigConfig
from hil.sim.plant import RigPlant
from hil.sim.sensors import SensorReading

__all__ = ["DEFAULT_GAINS", "TUNING_GRID", "TUNING_LIMITS", "SkyhookController",
           "SkyhookGains", "select_gains"]


@dataclass(frozen=True)
class SkyhookGains:
    c_sky_ns_per_m: float = 2000.0
    c_ground_ns_per_m: float = 0.0
    damper_cancel: float = 0.0
    velocity_highpass_hz: float = 0.2
    rattle_rate_lowpass_hz: float = 150.0

    def __post_init__(self) -> None:
        for name in ("c_sky_ns_per_m", "c_ground_ns_per_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"skyhook {name} = {v!r}: must be finite and >= 0")
        if not (math.isfinite(self.damper_cancel) and 0.0 <= self.damper_cancel <= 1.0):
            raise ValueError(f"skyhook damper_cancel = {self.damper_cancel!r}: allowed [0, 1]")
        for name in ("velocity_highpass_hz", "rattle_rate_lowpass_hz"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"skyhook {name} = {v!r}: must be finite and > 0")


#: (c_sky [Ns/m], c_ground [Ns/m], damper_cancel) grid of the tuning search
#: (0, 0, 0) = zero force reference: what the closed, force-controlled actuator costs
TUNING_GRID: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.0), *(
    (cs, cg, kc) for cs in (1000.0, 2000.0, 3000.0, 4000.0, 6000.0, 8000.0, 16000.0)
    for cg in (0.0, 1000.0) for kc in (0.0, 0.25, 0.375, 0.5, 0.625, 0.75, 1.0)))
#: ratio-to-passive limits a tuned setting must meet: rattlespace RMS no larger than
#: passive (the thesis's own constraint for weight set 1) and dynamic tire load RMS at
#: most 1.5 x passive (no wheel hop traded for comfort)
TUNING_LIMITS = {"rattlespace_rms_m": 1.0, "tire_load_rms_ratio": 1.5}
#: result of the tuning search with the default configuration (see docs/study.md; with
#: the force loop's flow feedforward, docs/design.md section 7)
DEFAULT_GAINS = SkyhookGains(4000.0, 0.0, 0.625)


def select_gains(rows: Sequence[dict[str, float]],
                 limits: dict[str, float] | None = None) -> SkyhookGains:
    """Pick the tuned gains from search rows holding ``c_sky_ns_per_m``,
    ``c_ground_ns_per_m``, ``damper_cancel`` and ratio-to-passive metrics ``<metric>_ratio``: lowest
    ``absorbed_power_ratio`` among the rows within ``limits``; if none qualifies, the
    row with the smallest worst-limit excess.  Raises ValueError on no rows."""
    if not rows:
        raise ValueError("no skyhook tuning rows")
    lim = TUNING_LIMITS if limits is None else limits

    def excess(r: dict[str, float]) -> float:
        return max(r[f"{k}_ratio"] / v for k, v in lim.items())

    def bad(r: dict[str, float]) -> bool:
        return not all(math.isfinite(r[f"{k}_ratio"]) for k in lim) or bool(r.get("unstable"))

    ok = [r for r in rows if not bad(r) and excess(r) <= 1.0]
    if ok:
        best = min(ok, key=lambda r: r["absorbed_power_ratio"])
    else:
        cand = [r for r in rows if not bad(r)] or list(rows)
        best = min(cand, key=excess)
    return SkyhookGains(float(best["c_sky_ns_per_m"]), float(best["c_ground_ns_per_m"]),
                        float(best["damper_cancel"]))


class SkyhookController:
    """Skyhook/groundhook from measured acceleration and rattlespace (study interface)."""

    name = "skyhook"

    def __init__(self, cfg: RigConfig, gains: SkyhookGains = DEFAULT_GAINS) -> None:
        self.gains = gains
        self.dt_s = cfg.sample_time_s
        self.c_cancel_ns_per_m = gains.damper_cancel * cfg.vehicle.suspension_damping_ns_per_m
        self._leak = math.exp(-2.0 * math.pi * gains.velocity_highpass_hz * self.dt_s)
        self._lp = 1.0 - math.exp(-2.0 * math.pi * gains.rattle_rate_lowpass_hz * self.dt_s)
        self.reset()

    def reset(self) -> None:
        self.body_velocity_mps = 0.0
        self.rattle_rate_mps = 0.0
        self._r_prev = math.nan
        self._fault = False

    @property
    def fault(self) -> bool:
        return self._fault

    @property
    def wheel_velocity_mps(self) -> float:
        return self.body_velocity_mps + self.rattle_rate_mps

    def force(self, rattlespace_m: float, accel_mps2: float) -> float:
        """One tick from the LVDT [m] and accelerometer [m/s^2] readings; never raises."""
        if not (math.isfinite(rattlespace_m) and math.isfinite(accel_mps2)):
            self._fault = True
            return 0.0
        self.body_velocity_mps = self._leak * self.body_velocity_mps + accel_mps2 * self.dt_s
        if not math.isnan(self._r_prev):
            raw = (rattlespace_m - self._r_prev) / self.dt_s
            self.rattle_rate_mps += self._lp * (raw - self.rattle_rate_mps)
        self._r_prev = rattlespace_m
        g = self.gains
        return -g.c_sky_ns_per_m * self.body_velocity_mps \
            + g.c_ground_ns_per_m * self.wheel_velocity_mps \
            - self.c_cancel_ns_per_m * self.rattle_rate_mps

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        return self.force(reading.rattlespace_m, reading.accel_mps2)
