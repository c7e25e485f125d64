"""Summary metrics of a recording: the whole run, and passive vs active side by side.

Computed from the measured signals (independent of the controller's own view), filters
from :mod:`controller.metrics` run over the whole series and are then averaged per phase:

* absorbed power proxy: mean square of the sprung acceleration through the thesis's
  human-body filter F(s) of the recorded configuration [(m/s²)²];
* ISO 2631 Wk-weighted RMS acceleration, acceleration RMS, rattlespace RMS / peak;
* measured actuator force RMS, force reference RMS as computed and as applied, force
  tracking error RMS (applied reference minus measured force, while active);
* loop wake-up lateness percentiles, compute-time p99 and overrun ticks;
* bump-stop contact: time with the LVDT reading on a stop (the stop-contact monitor's
  contact test, :mod:`controller.stop_contact`, on the recorded configuration), contact
  episodes, and the stop-contact monitor's degradations (StepFlag.STOP_DEGRADED rising
  edges in ``/controller/internals.flags``).
* the wheel-hop frequency of each phase: an AR(2) fit on the band-passed LVDT reading
  (:mod:`controller.wheel_hop`); a tire change between runs under the same law shows
  there, NaN under 5 s of readings; and, from the passive phase's, the tire's stiffness
  against the configured tire (:func:`controller.wheel_hop.tire_stiffness_scale` on the
  recording's configuration, with the sprung mass, spring rate and damping the
  controller estimated at the end of the active phase where it ran: the wheel hop moves
  with them too).  The law moves the wheel hop, so the active phase has no such row.
* the controller's own estimates at the end of each phase, as recorded: sprung mass,
  spring rate and damping (docs/design.md §10), and the runtime's passive wheel-hop
  frequency and tire stiffness (``/controller/internals.wheel_hop_hz``,
  ``tire_stiffness_est``, docs/design.md §11: held while armed, so the active phase
  shows the last passive estimate); NaN where a recording lacks the field.

"Passive" is every tick with the valve off (:attr:`~rig.report.series.Phase.PASSIVE` and
:attr:`~rig.report.series.Phase.FAULT`: the bypass is open either way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from controller.arrays import FloatArray
from controller.config import RigConfig
from controller.metrics import filter_signal, wk_tf
from controller.runtime.kernels import StepFlag
from controller.stop_contact import EPISODE_GAP_S
from controller.wheel_hop import tire_stiffness_scale, wheel_hop_frequency_hz
from rig.report.series import Phase, RunSeries

__all__ = ["SUMMARY_ROWS", "SummaryRow", "phase_metrics", "run_metrics", "stop_contact"]


@dataclass(frozen=True)
class SummaryRow:
    """One line of the passive-vs-active table."""

    key: str
    label: str
    unit: str
    source: str          # the recording's channel.field it is computed from
    digits: int = 4      # significant digits shown
    ratio: bool = True   # whether active / passive means something


SUMMARY_ROWS: tuple[SummaryRow, ...] = (
    SummaryRow("time_s", "time", "s", "/rig/signals.valve_enable", 3, ratio=False),
    SummaryRow("absorbed_power_proxy", "absorbed power proxy (F(s)-filtered accel, "
               "mean square)", "(m/s²)²", "/rig/signals.sprung_accel_mps2"),
    SummaryRow("wk_rms_mps2", "ISO 2631 Wk-weighted accel RMS", "m/s²",
               "/rig/signals.sprung_accel_mps2"),
    SummaryRow("accel_rms_mps2", "sprung acceleration RMS", "m/s²",
               "/rig/signals.sprung_accel_mps2"),
    SummaryRow("rattlespace_rms_mm", "rattlespace RMS", "mm", "/rig/signals.rattlespace_m"),
    SummaryRow("rattlespace_peak_mm", "rattlespace peak |x|", "mm",
               "/rig/signals.rattlespace_m"),
    SummaryRow("force_meas_rms_n", "measured actuator force RMS", "N",
               "/rig/signals.force_meas_n", ratio=False),
    SummaryRow("force_ref_applied_rms_n", "force reference RMS, applied", "N",
               "/rig/signals.force_ref_n", ratio=False),
    SummaryRow("force_ref_computed_rms_n", "force reference RMS, computed by the bank",
               "N", "/rig/signals.force_ref_n", ratio=False),
    SummaryRow("tracking_error_rms_n", "force tracking error RMS", "N",
               "/rig/signals.force_ref_n − force_meas_n", ratio=False),
    SummaryRow("stop_contact_s", "time on the bump stops (LVDT)", "s",
               "/rig/signals.rattlespace_m", 3, ratio=False),
    SummaryRow("stop_contact_episodes", "bump-stop contact episodes", "",
               "/rig/signals.rattlespace_m", 6, ratio=False),
    SummaryRow("stop_degradations", "stop-contact degradations", "",
               "/controller/internals.flags", 6, ratio=False),
    SummaryRow("sprung_mass_est_kg", "sprung-mass estimate at the end of the phase", "kg",
               "/controller/internals.sprung_mass_est_kg", ratio=False),
    SummaryRow("spring_rate_est_n_per_m", "spring-rate estimate at the end of the phase",
               "N/m", "/controller/internals.spring_rate_est_n_per_m", ratio=False),
    SummaryRow("damping_est_ns_per_m", "damping estimate at the end of the phase", "N s/m",
               "/controller/internals.damping_est_ns_per_m", ratio=False),
    SummaryRow("tire_stiffness_est", "tire-stiffness estimate at the end of the phase",
               "x configured", "/controller/internals.tire_stiffness_est", 3, ratio=False),
    SummaryRow("wheel_hop_est_hz", "passive wheel-hop frequency estimate at the end of "
               "the phase", "Hz", "/controller/internals.wheel_hop_hz", 3, ratio=False),
    SummaryRow("comfort_share_mean", "travel-schedule comfort share, mean", "",
               "/controller/internals.comfort_share", 3, ratio=False),
    SummaryRow("ride_height_max_m", "ride height (mean LVDT reading from mid-travel), "
               "largest |value|", "m", "/controller/internals.ride_height_m", 3, ratio=False),
    SummaryRow("wheel_hop_hz", "wheel-hop frequency (AR(2) fit on the LVDT, 5-20 Hz)",
               "Hz", "/rig/signals.rattlespace_m", 3, ratio=False),
    SummaryRow("tire_stiffness_scale", "tire stiffness from the passive wheel hop "
               "(x the configured tire)", "", "/rig/signals.rattlespace_m", 3, ratio=False),
    SummaryRow("no_rule_fired_pct", "ticks on which no fuzzy rule fired", "%",
               "/controller/internals.flags", 3, ratio=False),
    SummaryRow("lateness_p50_us", "wake-up lateness p50", "µs", "/rig/timing.wake_late_s"),
    SummaryRow("lateness_p99_us", "wake-up lateness p99", "µs", "/rig/timing.wake_late_s"),
    SummaryRow("lateness_max_us", "wake-up lateness max", "µs", "/rig/timing.wake_late_s"),
    SummaryRow("compute_p99_us", "compute time p99", "µs", "/rig/timing.compute_s"),
    SummaryRow("overrun_ticks", "overrun ticks", "", "/rig/timing.overrun", 6),
)


def _rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def _pct(x: FloatArray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else math.nan


def _max(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(x.max()) if x.size else math.nan


def stop_contact(s: RunSeries, mask: NDArray[np.bool_] | None = None
                 ) -> tuple[float, int, int]:
    """(time with the LVDT reading on a bump stop [s], contact episodes, stop-contact
    degradations) over the ticks of ``mask`` (default: all).  Contact and episodes follow
    the runtime's monitor (controller/stop_contact.py): beyond the stop less
    ``safety.stop_contact_band_m``; an episode starts on a contact tick after at least
    ``EPISODE_GAP_S`` without contact."""
    cfg = s.cfg
    centre, travel = cfg.design.bump_stop_centre_lvdt_m, cfg.vehicle.rattlespace_travel_m
    band = cfg.safety.stop_contact_band_m
    rs = s.signals["rattlespace_m"]
    m = np.ones(rs.size, dtype=bool) if mask is None else mask
    with np.errstate(invalid="ignore"):
        contact = ((rs > centre + travel - band) | (rs < centre - travel + band)) & m
    idx = np.flatnonzero(contact)
    gap = max(1, round(EPISODE_GAP_S / s.dt_s))
    episodes = int(idx.size > 0) + int(np.count_nonzero(np.diff(idx) - 1 >= gap))
    f = s.flags
    deg = (f >= 0) & ((f & int(StepFlag.STOP_DEGRADED)) != 0) if f.size == rs.size \
        else np.zeros(rs.size, dtype=bool)
    rises = deg & ~np.r_[False, deg[:-1]] & m
    return float(idx.size * s.dt_s), episodes, int(np.count_nonzero(rises))
def _last(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(x[-1]) if x.size else math.nan


def _last_in(x: FloatArray, m: NDArray[np.bool_]) -> float:
    """:func:`_last` of the ticks ``m`` of a per-tick series (NaN: the series was not
    recorded, so it has not one value per tick)."""
    return _last(x[m]) if x.size == m.size else math.nan


def _filtered(s: RunSeries) -> tuple[FloatArray, FloatArray]:
    """Sprung acceleration through F(s) and through ISO 2631 Wk, over the whole run."""
    acc = np.nan_to_num(s.signals["sprung_accel_mps2"])
    if not acc.size:
        return acc, acc
    d = s.cfg.design
    num, den = np.asarray(d.human_filter_num, float), np.asarray(d.human_filter_den, float)
    wn, wd = wk_tf()
    return filter_signal(acc, num, den, s.dt_s), filter_signal(acc, wn, wd, s.dt_s)


def run_metrics(s: RunSeries) -> dict[str, float | int | str]:
    """Whole-run summary metrics."""
    dt = s.dt_s
    acc = np.nan_to_num(s.signals["sprung_accel_mps2"])
    rs = s.signals["rattlespace_m"]
    acc_f, acc_wk = _filtered(s)
    late = s.timing["wake_late_s"] * 1e6
    faults = [e for e in s.events if e.get("kind") == "fault"]
    contact_s, episodes, stop_deg = stop_contact(s)
    return {
        "duration_s": float(s.t_s[-1] + dt) if s.t_s.size else 0.0,
        "ticks": int(s.tick.size),
        "time_active_s": float(np.sum(s.phase == Phase.ACTIVE) * dt),
        "time_fault_s": float(np.sum(s.phase == Phase.FAULT) * dt),
        "accel_rms_mps2": _rms(acc),
        "absorbed_power_proxy": float(np.mean(acc_f * acc_f)) if acc.size else math.nan,
        "wk_rms_mps2": _rms(acc_wk),
        "rattlespace_rms_mm": 1e3 * _rms(rs),
        "rattlespace_peak_mm": 1e3 * _max(np.abs(rs)),
        "force_meas_rms_n": _rms(s.signals["force_meas_n"]),
        "force_tracking_rms_error_n (active)": _rms(s.tracking_error_n),
        "lateness_p50_us": _pct(late, 50), "lateness_p99_us": _pct(late, 99),
        "lateness_max_us": _max(late),
        "compute_p99_us": _pct(s.timing["compute_s"] * 1e6, 99),
        "stop_contact_s": contact_s,
        "stop_contact_episodes": episodes,
        "stop_degradations": stop_deg,
        "faults": len(faults),
        "sprung_mass_est_kg (end)": _last(s.sprung_mass_est_kg),
        "recording": "complete" if s.scan.complete else f"incomplete: {s.scan.stopped_at}",
    }


def phase_metrics(s: RunSeries) -> dict[str, dict[str, float]]:
    """``{"passive": {...}, "active": {...}}`` with the keys of :data:`SUMMARY_ROWS`
    (NaN where a phase has no ticks or the quantity does not apply)."""
    acc_f, acc_wk = _filtered(s)
    acc = s.signals["sprung_accel_mps2"]
    rs = s.signals["rattlespace_m"]
    active = s.phase == Phase.ACTIVE
    out: dict[str, dict[str, float]] = {}
    for name, m in (("passive", ~active), ("active", active)):
        late = s.timing["wake_late_s"][m] * 1e6
        contact_s, episodes, stop_deg = stop_contact(s, m)
        phases = (Phase.ACTIVE,) if name == "active" else (Phase.PASSIVE, Phase.FAULT)
        out[name] = {
            "time_s": sum(s.time_in(p) for p in phases),        # by the loop clock
            "absorbed_power_proxy": float(np.mean(acc_f[m] ** 2)) if m.any() else math.nan,
            "wk_rms_mps2": _rms(acc_wk[m]),
            "accel_rms_mps2": _rms(acc[m]),
            "rattlespace_rms_mm": 1e3 * _rms(rs[m]),
            "rattlespace_peak_mm": 1e3 * _max(np.abs(rs[m])),
            "force_meas_rms_n": _rms(s.signals["force_meas_n"][m]),
            "force_ref_applied_rms_n": _rms(s.force_ref_applied_n[m]),
            "force_ref_computed_rms_n": _rms(s.signals["force_ref_n"][m]),
            "tracking_error_rms_n": _rms(s.tracking_error_n[m]),
            "lateness_p50_us": _pct(late, 50),
            "lateness_p99_us": _pct(late, 99),
            "lateness_max_us": _max(late),
            "compute_p99_us": _pct(s.timing["compute_s"][m] * 1e6, 99),
            "overrun_ticks": float(np.nansum(s.timing["overrun"][m])),
            "stop_contact_s": contact_s,
            "stop_contact_episodes": float(episodes),
            "stop_degradations": float(stop_deg),
            "sprung_mass_est_kg": _last_in(s.sprung_mass_est_kg, m),
            "spring_rate_est_n_per_m": _last_in(s.spring_rate_est_n_per_m, m),
            "damping_est_ns_per_m": _last_in(s.damping_est_ns_per_m, m),
            "tire_stiffness_est": _last_in(s.tire_stiffness_est, m),
            "wheel_hop_est_hz": _last_in(s.wheel_hop_hz, m),
            "comfort_share_mean": (float(np.nanmean(s.comfort_share[m]))
                                   if s.comfort_share.size == m.size and m.any()
                                   and np.isfinite(s.comfort_share[m]).any() else math.nan),
            "ride_height_max_m": (_max(np.abs(s.ride_height_m[m]))
                                  if s.ride_height_m.size == m.size else math.nan),
            "wheel_hop_hz": wheel_hop_frequency_hz(rs, s.dt_s, m),
            "tire_stiffness_scale": math.nan,
            "no_rule_fired_pct": (100.0 * float(s.no_rule_fired[m].mean())
                                  if m.any() and np.any(s.flags[m] >= 0) else math.nan),
        }
    out["passive"]["tire_stiffness_scale"] = tire_stiffness_scale(
        out["passive"]["wheel_hop_hz"], _estimated_rig(s, active), dt_s=s.dt_s)
    return out


def _estimated_rig(s: RunSeries, active: NDArray[np.bool_]) -> RigConfig:
    """The recording's configuration with the sprung mass, spring rate and damping the
    controller estimated at the end of the active phase, where all three were recorded
    there (with the valve off the estimator cannot tell their common scale,
    docs/design.md §11); else as configured."""
    est = (_last_in(s.sprung_mass_est_kg, active), _last_in(s.spring_rate_est_n_per_m, active),
           _last_in(s.damping_est_ns_per_m, active))
    if not all(math.isfinite(x) and x > 0.0 for x in est):
        return s.cfg
    return s.cfg.replace(vehicle={"sprung_mass_kg": est[0],
                                  "suspension_stiffness_n_per_m": est[1],
                                  "suspension_damping_ns_per_m": est[2]})
