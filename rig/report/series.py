"""Per-tick series of a recording, its configuration and its phases.

:func:`load_series` decodes ``/rig/signals``, ``/controller/internals``, ``/rig/timing``
and ``/rig/events`` through the recording scanner (:func:`rig.recording.scan.scan_recording`).
Every tick belongs to one :class:`Phase`: ACTIVE while the valve is driven
(``valve_enable`` = 1), FAULT while a fault is latched, PASSIVE otherwise (INACTIVE,
STOPPING).  In PASSIVE and FAULT the rig's bypass is open and the suspension is passive.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.arrays import FloatArray
from controller.config import (
    ConfigError,
    RigConfig,
    config_from_bytes,
    default_config,
    layer_params,
)
from controller.runtime.kernels import StepFlag
from rig.recording.scan import RecordingError, ScanResult, scan_recording, split_json
from rig.recording.schema import (
    CONFIG_ATTACHMENT,
    DESIGN_ATTACHMENT,
    NONFINITE_NUMBER,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_SIGNALS,
    TOPIC_TIMING,
    event_from_message,
)
from rig.wire.protocol import LifecycleState

__all__ = ["LIFECYCLE_NAMES", "SIGNAL_FIELDS", "TIMING_FIELDS", "Phase", "RunSeries", "Segment",
           "load_series"]


#: ``/rig/signals`` fields read as numbers
SIGNAL_FIELDS = ("rattlespace_m", "sprung_accel_mps2", "force_meas_n", "force_ref_n",
                 "spool_cmd", "valve_enable", "sensor_counter", "sensor_age_ticks")
#: ``/rig/timing`` fields read as numbers (booleans as 0 / 1)
TIMING_FIELDS = ("wake_late_s", "compute_s", "period_s", "overrun", "overruns_total")
#: lifecycle states in DBC order
LIFECYCLE_NAMES = tuple(s.name for s in LifecycleState)
#: ``/controller/internals`` fields with one value per model
PER_MODEL_FIELDS = ("q", "firing_weight", "probability", "u_model")


class Phase(IntEnum):
    """What the suspension was doing at a tick (shaded alike on every plot)."""

    PASSIVE = 0     # valve off, no fault latched (INACTIVE, STOPPING)
    ACTIVE = 1      # valve driven by the controller
    FAULT = 2       # fault latched, valve off

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class Segment:
    """Ticks ``start`` .. ``stop - 1`` in one phase; times in seconds since the first tick
    (``t_stop_s`` is the end of the last tick)."""

    start: int
    stop: int
    phase: Phase
    t_start_s: float
    t_stop_s: float


@dataclass
class RunSeries:
    """Per-tick series of a recording (NaN where a value was not recorded)."""

    path: Path
    scan: ScanResult
    tick: NDArray[np.int64]
    t_s: FloatArray                       # seconds since the first tick
    t0_ns: int                            # loop clock of the first tick
    signals: dict[str, FloatArray]
    lifecycle: list[str]
    fault: list[str]                      # latched fault code per tick, "" = none
    per_model: dict[str, FloatArray]      # (n, J): q, firing_weight, probability, u_model
    timing: dict[str, FloatArray]
    events: list[dict[str, Any]]
    model_names: list[str] = field(default_factory=list)
    config: RigConfig | None = None       # the recording's config.toml (None: unreadable)
    config_problem: str = ""              # why ``config`` is None
    flags: NDArray[np.int64] = field(    # /controller/internals.flags (-1: not recorded)
        default_factory=lambda: np.zeros(0, np.int64))
    #: /controller/internals.sprung_mass_est_kg per tick (NaN: not recorded)
    sprung_mass_est_kg: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: /controller/internals.comfort_share per tick (NaN: not recorded)
    comfort_share: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: /controller/internals.ride_height_m per tick (NaN: not recorded)
    ride_height_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: /controller/internals.spring_rate_est_n_per_m per tick (NaN: not recorded)
    spring_rate_est_n_per_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: /controller/internals.damping_est_ns_per_m per tick (NaN: not recorded)
    damping_est_ns_per_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: (n, 3) sprung mass [kg], spring rate [N/m] and damping [N s/m] of the layer the
    #: bank ran each tick (a layered bank, docs/design.md §11; NaN rows otherwise)
    layer_mkc: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    #: /controller/internals.wheel_hop_hz per tick: the runtime's passive wheel-hop
    #: frequency [Hz] (NaN: not yet estimated, or not recorded)
    wheel_hop_hz: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: /controller/internals.tire_stiffness_est per tick: the runtime's tire stiffness
    #: [x configured] (NaN: not yet estimated, or not recorded)
    tire_stiffness_est: FloatArray = field(default_factory=lambda: np.zeros(0))

    def no_sensor_data(self) -> str | None:
        """Why the run has nothing to show -- tick records, but on none of them a fresh
        SensorData reading (``sensor_age_ticks`` never 0: the loop never received the
        rig's sensor frames, e.g. nobody on the bus) -- or None."""
        age = self.signals["sensor_age_ticks"]
        if not np.isfinite(age).any() or (age == 0).any():
            return None
        return (f"no sensor data: {self.tick.size} tick records, none with a fresh "
                "SensorData reading (/rig/signals.sensor_age_ticks never 0: the loop "
                "never received the rig's sensor frames)")

    @property
    def dt_s(self) -> float:
        d = np.diff(self.t_s)
        return float(np.median(d)) if d.size else 1e-3

    @property
    def cfg(self) -> RigConfig:
        """The recording's configuration, or the defaults when it could not be read."""
        return self.config if self.config is not None else default_config()

    @cached_property
    def phase(self) -> NDArray[np.int8]:
        """:class:`Phase` of every tick."""
        out = np.full(self.tick.size, Phase.PASSIVE, dtype=np.int8)
        out[np.array([x == "FAULT" for x in self.lifecycle], dtype=bool)] = Phase.FAULT
        out[self.signals["valve_enable"] > 0] = Phase.ACTIVE
        return out

    @cached_property
    def segments(self) -> list[Segment]:
        """Maximal runs of ticks in one phase, in time order."""
        ph = self.phase
        if not ph.size:
            return []
        cuts = np.flatnonzero(np.diff(ph)) + 1
        starts = np.r_[0, cuts]
        stops = np.r_[cuts, ph.size]
        ends = np.r_[self.t_s[1:], self.t_s[-1] + self.dt_s]
        return [Segment(int(a), int(b), Phase(int(ph[a])), float(self.t_s[a]),
                        float(ends[b - 1])) for a, b in zip(starts, stops, strict=True)]

    def time_in(self, phase: Phase) -> float:
        """Seconds spent in ``phase``."""
        return sum(g.t_stop_s - g.t_start_s for g in self.segments if g.phase is phase)

    @cached_property
    def no_rule_fired(self) -> NDArray[np.bool_]:
        """Ticks on which no fuzzy rule fired (StepFlag.NO_RULE_FIRED): the blend had no
        weight and the bank's force is ``fuzzy.no_fire_fallback``'s."""
        f = self.flags
        return (f >= 0) & ((f & int(StepFlag.NO_RULE_FIRED)) != 0)

    @cached_property
    def force_ref_applied_n(self) -> FloatArray:
        """The force reference the PI force loop tracked: ``force_ref_n`` saturated at
        ``force_loop.force_limit_n`` while the valve is driven, 0 otherwise.

        The bank computes ``force_ref_n`` in every state (docs/service.md) but only
        ACTIVE applies it: with the valve off the ValveCommand carries Enable = 0 and
        ForceReference = 0 and the bypass is open."""
        lim = self.cfg.force_loop.force_limit_n
        on = self.signals["valve_enable"] > 0
        return np.where(on, np.clip(self.signals["force_ref_n"], -lim, lim), 0.0)

    @cached_property
    def tracking_error_n(self) -> FloatArray:
        """Applied force reference minus measured force while the valve is driven
        (NaN otherwise)."""
        on = self.signals["valve_enable"] > 0
        return np.where(on, self.force_ref_applied_n - self.signals["force_meas_n"], np.nan)

    def event_time_s(self, event: dict[str, Any]) -> float:
        """Seconds since the first tick of an event record (by its ``t_ns``)."""
        t_ns, tick = event.get("t_ns"), event.get("tick")
        if isinstance(t_ns, int):
            return (t_ns - self.t0_ns) * 1e-9
        if isinstance(tick, int) and self.tick.size:
            return (tick - int(self.tick[0])) * self.dt_s
        return math.nan


def _f(v: Any) -> float:
    """A recorded number; NaN for :data:`NONFINITE_NUMBER` or anything that is not a
    number."""
    return float(v) if isinstance(v, int | float) and v != NONFINITE_NUMBER else math.nan


def _matrix(rows: list[Any], width: int) -> FloatArray:
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        if isinstance(r, list) and r:
            k = min(width, len(r))
            out[i, :k] = [_f(x) for x in r[:k]]
    return out


def _bank_matrix(rows: list[Any], models: list[Any], width: int) -> FloatArray:
    """Per-model values of a layered bank's records (one column per running model, the
    ``models`` field its bank index) spread over the bank's ``width`` models: 0 where a
    model did not run (as the runtime reads its inactive filters), NaN where the record
    has no value.  A column whose index is not a model of the bank is left out."""
    out = np.full((len(rows), width), np.nan)
    for i, (r, m) in enumerate(zip(rows, models, strict=True)):
        if not (isinstance(r, list) and isinstance(m, list)):
            continue
        out[i, :] = 0.0
        for x, j in zip(r, m, strict=False):
            if isinstance(j, int) and 0 <= j < width:
                out[i, j] = _f(x)
    return out


def _objects(path: str | Path, topic: str, joined: bytes,
             seqs: list[int]) -> list[dict[str, Any]]:
    """The JSON objects of a topic's payloads; RecordingError naming the first that is
    not one."""
    try:
        objs = split_json(joined)
    except (ValueError, RecursionError) as exc:   # JSONDecodeError, UnicodeDecodeError
        raise RecordingError(f"{path}: a {topic} payload is not JSON "
                             f"({type(exc).__name__}: {str(exc)[:120]})") from None
    if len(objs) != len(seqs):
        raise RecordingError(f"{path}: {len(seqs)} {topic} messages hold {len(objs)} JSON "
                             "values, expected one object each")
    for i, obj in enumerate(objs):
        if not isinstance(obj, dict):
            raise RecordingError(f"{path}: {topic} message {_which(i, seqs)} is a JSON "
                                 f"{type(obj).__name__}, expected an object")
    return objs


def _which(i: int, seqs: list[int]) -> str:
    return f"{i} (sequence {seqs[i]})" if i < len(seqs) else str(i)


def _require_int(path: str | Path, topic: str, objs: list[dict[str, Any]], seqs: list[int],
                 *keys: str) -> None:
    for i, obj in enumerate(objs):
        for key in keys:
            v = obj.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or not -(1 << 63) <= v < 1 << 63:
                what = "has no" if key not in obj else \
                    f"has {key} = {str(v)[:40]!r}, not a 64-bit"
                raise RecordingError(f"{path}: {topic} message {_which(i, seqs)} {what} "
                                     f"integer '{key}'")


def _events(path: str | Path, msgs: list[dict[str, Any]], seqs: list[int]
            ) -> list[dict[str, Any]]:
    """The events with their detail decoded; RecordingError naming the first that is
    malformed."""
    out = []
    for i, m in enumerate(msgs):
        try:
            out.append(event_from_message(m))
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{path}: {TOPIC_EVENTS} message {_which(i, seqs)} is not "
                                 f"an event ({type(exc).__name__}: {str(exc)[:80]})") from None
    return out


def load_series(path: str | Path) -> RunSeries:
    """Decode signals, internals, timing and events of a recording (errors: see
    :func:`rig.recording.scan.scan_recording`)."""
    parts: dict[str, list[tuple[bytes, NDArray[np.uint32]]]] = {
        TOPIC_SIGNALS: [], TOPIC_INTERNALS: [], TOPIC_TIMING: [], TOPIC_EVENTS: []}

    def collector(topic: str) -> Any:
        return lambda joined, seqs: parts[topic].append((joined, seqs))

    scan = scan_recording(path, {t: collector(t) for t in parts})

    def decoded(topic: str) -> tuple[list[dict[str, Any]], list[int]]:
        seqs = [int(q) for _, s in parts[topic] for q in s]
        return _objects(path, topic, b"".join(j for j, _ in parts[topic]), seqs), seqs

    recs, rec_seqs = decoded(TOPIC_SIGNALS)
    where = {q: i for i, q in enumerate(rec_seqs)}
    for topic in (TOPIC_INTERNALS, TOPIC_TIMING):  # parts of the same tick record
        for obj, q in zip(*decoded(topic), strict=True):
            i = where.get(q)
            if i is not None:
                recs[i].update(obj)
    _require_int(path, TOPIC_SIGNALS, recs, rec_seqs, "tick", "t_ns")
    event_msgs, event_seqs = decoded(TOPIC_EVENTS)
    _require_int(path, TOPIC_EVENTS, event_msgs, event_seqs, "tick")
    events = _events(path, event_msgs, event_seqs)
    n = len(recs)
    tick = np.array([r["tick"] for r in recs], dtype=np.int64)
    t_ns = np.array([r["t_ns"] for r in recs], dtype=np.int64)
    t0_ns = int(t_ns[0]) if n else 0
    t_s: FloatArray = ((t_ns - t0_ns) * 1e-9).astype(np.float64)
    signals = {k: np.array([_f(r.get(k)) for r in recs]) for k in SIGNAL_FIELDS}
    timing = {k: np.array([_f(r.get(k)) for r in recs]) for k in TIMING_FIELDS}
    J = max((len(qs) for r in recs if isinstance(qs := r.get("q"), list)), default=0)
    models = [r.get("models") for r in recs]
    names = _design_model_names(scan)
    if len(names) > J and any(isinstance(m, list) for m in models):
        J = len(names)          # a layered bank: its records carry the running layer
        per_model = {k: _bank_matrix([r.get(k) for r in recs], models, J)
                     for k in PER_MODEL_FIELDS}
    else:
        per_model = {k: _matrix([r.get(k) for r in recs], J) for k in PER_MODEL_FIELDS}
    flags = np.array([f if isinstance(f := r.get("flags"), int) else -1 for r in recs],
                     dtype=np.int64)
    def column(key: str) -> FloatArray:
        return np.array([_f(r.get(key)) for r in recs])

    config, problem = _config(scan)
    layers = _running_layers(config, models, J)
    return RunSeries(Path(path), scan, tick, t_s, t0_ns, signals,
                     [str(r.get("lifecycle", "")) for r in recs],
                     [str(r.get("fault", "")) for r in recs], per_model, timing, events,
                     _model_names(scan, J), config, problem, flags,
                     column("sprung_mass_est_kg"), column("comfort_share"),
                     column("ride_height_m"), column("spring_rate_est_n_per_m"),
                     column("damping_est_ns_per_m"), layers, column("wheel_hop_hz"),
                     column("tire_stiffness_est"))


def _running_layers(cfg: RigConfig | None, models: list[Any], n_models: int) -> FloatArray:
    """[M, K, C] of the layer each record's bank ran, from its first column's model
    index (layer major, the airborne model last: controller/runtime/mass_layers.py) and
    the layers of the recording's configuration; NaN rows for a one-layer bank, without
    a configuration or where a record has no valid index."""
    out = np.full((len(models), 3), np.nan)
    if cfg is None:
        return out
    mkc = np.array(layer_params(cfg), dtype=float)
    n_layers = mkc.shape[0]
    n_tire = (n_models - int(cfg.design.include_airborne_model)) // n_layers
    if n_layers < 2 or n_tire < 1:
        return out
    for i, m in enumerate(models):
        if isinstance(m, list) and m and isinstance(m[0], int) \
                and 0 <= m[0] < n_tire * n_layers:
            out[i] = mkc[m[0] // n_tire]
    return out


def _config(scan: ScanResult) -> tuple[RigConfig | None, str]:
    raw = scan.attachments.get(CONFIG_ATTACHMENT)
    damage = scan.damaged_attachments.get(CONFIG_ATTACHMENT)
    if damage:
        return None, f"its {CONFIG_ATTACHMENT} attachment is damaged ({damage})"
    if raw is None:
        return None, f"the recording has no {CONFIG_ATTACHMENT} attachment"
    try:
        return config_from_bytes(raw, CONFIG_ATTACHMENT), ""
    except ConfigError as exc:
        return None, f"its {CONFIG_ATTACHMENT} could not be read ({exc})"


def _design_model_names(scan: ScanResult, want: int = 0) -> list[str]:
    """The bank's model names: the recording's ``models`` metadata, else (or when it
    does not have ``want`` names) its design artifact's; [] without either."""
    raw = scan.rig_metadata.get("models")
    try:
        names = json.loads(raw) if raw else []
    except (json.JSONDecodeError, TypeError):
        names = []
    if isinstance(names, list) and names and (not want or len(names) == want):
        return [str(x) for x in names]
    if DESIGN_ATTACHMENT in scan.attachments:
        try:
            with np.load(io.BytesIO(scan.attachments[DESIGN_ATTACHMENT])) as npz:
                return [str(x) for x in npz["model_names"]]
        except (OSError, ValueError, KeyError):
            pass
    return []


def _model_names(scan: ScanResult, J: int) -> list[str]:
    """Model names of the design (:func:`_design_model_names`), one per column."""
    names = _design_model_names(scan, J)
    return names if len(names) == J else [f"model {j}" for j in range(J)]

