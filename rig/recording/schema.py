"""JSON schemas of the MCAP recording channels (``docs/recording.md``).

Every channel uses message encoding ``json`` and schema encoding ``jsonschema`` so that
Foxglove (and any MCAP tool) can decode and plot the fields without project code.

A tick record handed to :meth:`rig.recording.recorder.RunRecorder.tick` is one flat dict; the
writer splits it by key into up to three messages that share one MCAP ``sequence``:

* keys in :data:`SIGNAL_KEYS` and ``tick``         -> ``/rig/signals``
* keys in :data:`TIMING_KEYS` and ``tick``         -> ``/rig/timing``
* every other key (controller internals) + ``tick`` -> ``/controller/internals``

Each message also carries ``t_ns`` (the loop clock, see docs/recording.md) and the
signals message ``record_parts`` (how many messages the record has).  Keys ``t_ns`` and
``record_parts`` are therefore reserved in tick records.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from enum import IntEnum
from typing import Any, Final

from rig.recording.scene import FRAME_TRANSFORM_SCHEMA, SCENE_UPDATE_SCHEMA
from rig.wire.fault_descriptions import FAULT_DESCRIPTIONS

__all__ = [
    "CONFIG_ATTACHMENT",
    "DESIGN_ATTACHMENT",
    "EVENT_KINDS",
    "LOG_SCHEMA",
    "MESSAGE_ENCODING",
    "METADATA_NAME",
    "NONFINITE_NUMBER",
    "PARTS_KEY",
    "RECORDING_FORMAT_VERSION",
    "SCHEMA_ENCODING",
    "SIGNAL_KEYS",
    "TIMING_KEYS",
    "TOPICS",
    "TOPIC_CAN_RX",
    "TOPIC_CAN_TX",
    "TOPIC_EVENTS",
    "TOPIC_INTERNALS",
    "TOPIC_LOG",
    "TOPIC_SCENE",
    "TOPIC_SIGNALS",
    "TOPIC_TF",
    "TOPIC_TIMING",
    "LogLevel",
    "encode_json",
    "encode_message",
    "event_from_message",
    "event_message",
    "log_message",
    "schema_bytes",
    "split_record",
]

#: Bumped when a channel, field meaning or attachment name changes incompatibly.
#: 2: segment identity and end records (run id, index, sequence / tick ranges) and the
#: data-section CRC (rig.recording.segments)
#: 3: events also on ``/rig/log`` (foxglove.Log), the quarter-car picture on
#: ``/rig/scene`` (foxglove.SceneUpdate) and ``/tf`` (foxglove.FrameTransform), and the
#: identification excitation marked by ``excitation`` events
#: 4: one JSON type per field, so that Foxglove / Lichtblick convert every schema:
#: non-finite numbers are :data:`NONFINITE_NUMBER` (not null), ``fault`` is ``""``
#: without a fault, ``valve_enable`` 0 / 1, ``blending`` the mode code only, ``x_post``
#: flat (row-major), the event detail is JSON text in ``detail_json``, and the
#: ``foxglove.SceneUpdate`` arrays declare their items
RECORDING_FORMAT_VERSION: Final = 4
SCHEMA_ENCODING: Final = "jsonschema"
#: the metadata record that opens every segment (format version, run identity, settings)
METADATA_NAME: Final = "rig"
#: attachments of every segment: the configuration (TOML) and the design artifact (npz)
CONFIG_ATTACHMENT: Final = "config.toml"
DESIGN_ATTACHMENT: Final = "design.npz"
MESSAGE_ENCODING: Final = "json"

TOPIC_CAN_RX: Final = "/can/rx"
TOPIC_CAN_TX: Final = "/can/tx"
TOPIC_SIGNALS: Final = "/rig/signals"
TOPIC_INTERNALS: Final = "/controller/internals"
TOPIC_TIMING: Final = "/rig/timing"
TOPIC_EVENTS: Final = "/rig/events"
TOPIC_LOG: Final = "/rig/log"
TOPIC_SCENE: Final = "/rig/scene"
TOPIC_TF: Final = "/tf"
#: in /rig/signals: how many messages the tick record has (signals first)
PARTS_KEY: Final = "record_parts"
_RESERVED: Final = frozenset({"tick", "t_ns", PARTS_KEY})

#: Decoded rig signals and the loop's outputs (documented in docs/recording.md).
SIGNAL_KEYS: Final = frozenset({
    "rattlespace_m", "sprung_accel_mps2", "force_meas_n", "force_ref_n", "spool_cmd",
    "valve_enable", "lifecycle", "fault", "sensor_counter", "sensor_age_ticks",
})
#: Timing statistics of the loop.
TIMING_KEYS: Final = frozenset({
    "wake_late_s", "compute_s", "period_s", "overrun", "overrun_streak", "overruns_total",
    "dropped_recording", "dropped_telemetry",
})
#: Event kinds (``detail`` layout per kind in docs/recording.md).
EVENT_KINDS: Final = ("command", "lifecycle", "fault", "note", "excitation")

#: what a schema'd channel (recording and live view) writes for a non-finite number (NaN,
#: +-inf, a time not measured): JSON has no NaN and Foxglove's schema converter takes one
#: type per field, so no null either; the keys concerned are listed in ``nonfinite`` and
#: readers turn it back into NaN
NONFINITE_NUMBER: Final = -1e308
_NUM: Final[dict[str, Any]] = {"type": "number"}
_NUM_ARRAY: Final[dict[str, Any]] = {"type": "array", "items": _NUM}
_NONFINITE_KEYS: Final[dict[str, Any]] = {
    "type": "array", "items": {"type": "string"},
    "description": f"keys whose non-finite values were written as {NONFINITE_NUMBER:g}"}
_TICK: Final[dict[str, Any]] = {
    "tick": {"type": "integer", "minimum": 0, "description": "loop tick number"},
    "t_ns": {"type": "integer", "description": "loop clock [ns] (see metadata 'clock')"},
}


def _obj(title: str, props: dict[str, Any], required: list[str],
         additional: bool | dict[str, Any] = True, description: str = "") -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": {**_TICK, **props},
        "required": ["tick", "t_ns", *required],
        "additionalProperties": additional,
    }


CAN_FRAME_SCHEMA: Final = _obj(
    "rig.CanFrame",
    {
        "id": {"type": "integer", "minimum": 0, "maximum": 0x1FFFFFFF,
               "description": "arbitration id"},
        "data": {"type": "string", "pattern": "^([0-9a-f]{2}){0,64}$",
                 "description": "payload bytes, lowercase hex"},
        "dlc": {"type": "integer", "minimum": 0, "maximum": 64},
        "error_frame": {"type": "boolean",
                        "description": "present (true) only on a CAN error frame"},
        "extended_id": {"type": "boolean",
                        "description": "present (true) only on a 29-bit identifier"},
    },
    ["id", "data", "dlc"], additional=False,
    description="one raw CAN frame as the loop received (/can/rx) or sent (/can/tx) it",
)

SIGNALS_SCHEMA: Final = _obj(
    "rig.Signals",
    {
        "rattlespace_m": {**_NUM, "description": "LVDT about static, compression +"},
        "sprung_accel_mps2": {**_NUM, "description": "zs'' without gravity, up +"},
        "force_meas_n": {**_NUM, "description": "load-cell actuator force"},
        "force_ref_n": {**_NUM, "description": "blended force reference"},
        "spool_cmd": {**_NUM, "description": "normalised spool command sent"},
        "valve_enable": {"type": "integer", "minimum": 0, "maximum": 1,
                         "description": "1 = the valve is driven (ACTIVE)"},
        "lifecycle": {"type": "string"},
        "fault": {"type": "string", "description": "latched fault code, \"\" = none"},
        "sensor_counter": {"type": "integer"},
        "sensor_age_ticks": {"type": "integer"},
        "record_parts": {"type": "integer", "minimum": 1, "maximum": 3,
                         "description": "messages of this tick record (signals first)"},
        "nonfinite": _NONFINITE_KEYS,
    },
    [],
    description="decoded rig signals and loop outputs, one message per tick",
)

INTERNALS_SCHEMA: Final = _obj(
    "rig.ControllerInternals",
    {
        "q": {**_NUM_ARRAY, "description": "likelihood quotient per model"},
        "firing_weight": {**_NUM_ARRAY, "description": "fuzzy firing weight per model"},
        "probability": {**_NUM_ARRAY, "description": "normalised model probability"},
        "u_model": {**_NUM_ARRAY, "description": "force per model controller [N]"},
        "active": {"type": "array", "items": {"type": "boolean"}},
        "models": {"type": "array", "items": {"type": "integer"},
                   "description": "the bank's model index of each per-model column: the "
                   "models of the layer the bank runs (docs/design.md §11)"},
        "flags": {"type": "integer", "description": "StepFlag bits"},
        "blending": {"type": "integer", "minimum": 0,
                     "description": "bank mode code (controller.modes.Blending)"},
        "weight_set": {"type": "integer"},
        "sprung_mass_est_kg": {**_NUM, "description": "the controller's sprung-mass "
                               "estimate [kg] (controller/mass_estimator.py)"},
        "spring_rate_est_n_per_m": {**_NUM, "description": "the suspension spring rate "
                                    "the estimator fits beside the mass [N/m]"},
        "damping_est_ns_per_m": {**_NUM, "description": "the suspension damping the "
                                 "estimator fits beside the mass [N s/m]"},
        "wheel_hop_hz": {**_NUM, "description": "the passive rig's wheel-hop frequency "
                         "[Hz] the runtime fits on the band-passed LVDT while the load "
                         "cell reads no force (controller/wheel_hop.py; non-finite until "
                         "estimated, held while armed)"},
        "tire_stiffness_est": {**_NUM, "description": "the tire's stiffness against the "
                               "configured tire [x configured], from wheel_hop_hz "
                               "(non-finite until estimated; docs/design.md §11)"},
        "x_post": {**_NUM_ARRAY, "description": "(W, 4) estimates of the W models in "
                   "models, flat row-major: column k at [4k, 4k + 4)"},
        "xf": _NUM_ARRAY,
        "stop_contact_s": {**_NUM, "description": "bump-stop contact time in the "
                           "stop-contact monitor's window [s]"},
        "stop_degraded": {"type": "boolean", "description": "the stop-contact monitor has "
                          "the bank on its travel-conservative law"},
        "comfort_share": {**_NUM, "description": "the travel schedule's comfort-law share "
                          "of the force, 0..1 (1: weight set 2 alone, 0: weight set 1 "
                          "alone or the schedule off; docs/design.md §12)"},
        "ride_height_m": {**_NUM, "description": "ride height: the mean LVDT reading "
                          "about the stops' centre [m], compression positive (the "
                          "ride-height monitor, docs/design.md §9.9; bit 128 of flags "
                          "while it is off centre)"},
        "nonfinite": _NONFINITE_KEYS,
    },
    [],
    description="controller internals of one tick",
)

TIMING_SCHEMA: Final = _obj(
    "rig.Timing",
    {
        "wake_late_s": _NUM, "compute_s": _NUM, "period_s": _NUM,
        "overrun": {"type": "boolean"},
        "overrun_streak": {"type": "integer"}, "overruns_total": {"type": "integer"},
        "dropped_recording": {"type": "integer"}, "dropped_telemetry": {"type": "integer"},
        "nonfinite": _NONFINITE_KEYS,
    },
    [],
    description="loop timing of one tick",
)

EVENT_SCHEMA: Final = _obj(
    "rig.Event",
    {
        "kind": {"type": "string", "enum": list(EVENT_KINDS)},
        "detail_json": {"type": "string",
                        "description": "the detail (object, string or null) as JSON text"},
    },
    ["kind", "detail_json"], additional=False,
    description="lifecycle transitions, applied commands, faults, notes",
)

_TIME: Final[dict[str, Any]] = {
    "type": "object", "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    "required": ["sec", "nsec"],
}


class LogLevel(IntEnum):
    """foxglove.LogLevel (the well-known schema's numbers)."""

    UNKNOWN = 0
    DEBUG = 1
    INFO = 2
    WARNING = 3
    ERROR = 4
    FATAL = 5


#: the well-known ``foxglove.Log`` message (JSON form; Foxglove's Log panel reads it by
#: this schema name): the rig's events with a level, one line of text and the code
LOG_SCHEMA: Final[dict[str, Any]] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "foxglove.Log",
    "description": "A log message: one lifecycle transition, fault, command or note",
    "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "wall time of the event"},
        "level": {"title": "foxglove.LogLevel",
                  "oneOf": [{"title": lv.name, "const": int(lv)} for lv in LogLevel]},
        "message": {"type": "string"},
        "name": {"type": "string", "description": "event kind: lifecycle, fault, command, "
                 "note"},
        "file": {"type": "string", "description": "code of the event (fault code, command, "
                 "target state)"},
        "line": {"type": "integer", "minimum": 0, "description": "loop tick"},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}


#: topic -> schema
TOPICS: Final[dict[str, dict[str, Any]]] = {
    TOPIC_CAN_RX: CAN_FRAME_SCHEMA,
    TOPIC_CAN_TX: CAN_FRAME_SCHEMA,
    TOPIC_SIGNALS: SIGNALS_SCHEMA,
    TOPIC_INTERNALS: INTERNALS_SCHEMA,
    TOPIC_TIMING: TIMING_SCHEMA,
    TOPIC_EVENTS: EVENT_SCHEMA,
    TOPIC_LOG: LOG_SCHEMA,
    TOPIC_SCENE: SCENE_UPDATE_SCHEMA,
    TOPIC_TF: FRAME_TRANSFORM_SCHEMA,
}


def split_record(t_ns: int, record: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """One flat tick record -> ``[(topic, message), ...]`` by key (:data:`SIGNAL_KEYS`,
    :data:`TIMING_KEYS`, the rest internals); signals first, carrying
    :data:`PARTS_KEY`; internals and timing only when they have fields; matrices
    (``x_post``) flat, row-major.  The recording
    writer and the live Foxglove view publish exactly these messages."""
    tick = int(record["tick"])
    sig: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
    tim: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
    intl: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
    for k, v in record.items():
        if k in SIGNAL_KEYS:
            sig[k] = v
        elif k in TIMING_KEYS:
            tim[k] = v
        elif k not in _RESERVED:
            intl[k] = _flat(v)
    parts = [(TOPIC_SIGNALS, sig)]
    parts += [(t, m) for t, m in ((TOPIC_INTERNALS, intl), (TOPIC_TIMING, tim))
              if len(m) > 2]
    sig[PARTS_KEY] = len(parts)   # lets a reader spot a record torn by a crash
    return parts


def _flat(value: Any) -> Any:
    """A matrix (numpy array or list of lists) -> one flat row-major list (the schema
    converter of the Foxglove apps takes no arrays of arrays); anything else as it is."""
    if getattr(value, "ndim", 1) > 1:
        return value.ravel()
    if isinstance(value, list) and value and isinstance(value[0], list | tuple):
        return [x for row in value for x in row]
    return value


def _text(value: Any, limit: int = 300) -> str:
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def log_message(wall_ns: int, tick: int, kind: str, detail: Any) -> dict[str, Any]:
    """The ``foxglove.Log`` message of one event (``kind``/``detail`` as on
    ``/rig/events``).  Levels: a latched fault ERROR; a refused command, a bus exception
    or a degraded estimator or stop-contact monitor WARNING; everything else INFO."""
    level = LogLevel.INFO
    code = kind
    d = detail if isinstance(detail, Mapping) else {}
    if kind == "fault" or (kind == "lifecycle" and d.get("to") == "FAULT"):
        level = LogLevel.ERROR
        code = str(d.get("fault", "FAULT"))
        plain = FAULT_DESCRIPTIONS.get(code, "")
        message = f"FAULT {code}: {plain} ({d.get('reason', '')})" if plain \
            else f"FAULT {code}: {d.get('reason', '')}"
    elif kind == "lifecycle" and d:
        code = str(d.get("to", ""))
        message = f"{d.get('from')} -> {d.get('to')}: {d.get('reason', '')}"
    elif kind == "command" and d:
        code = str(d.get("command", "command"))
        if not d.get("accepted", True):
            level = LogLevel.WARNING
        arg = d.get("argument")
        message = (f"command {code}{'' if arg is None else f'({_text(arg, 60)})'} "
                   f"{'accepted' if d.get('accepted') else 'refused'}: "
                   f"{d.get('message', '')}")
    elif kind == "note" and "bus_exception" in d:
        level = LogLevel.WARNING
        code = f"bus_{d['bus_exception']}"
        message = f"CAN {d['bus_exception']} failed: {d.get('type', '')} {d.get('error', '')}"
    elif kind == "note" and "estimator" in d:
        degraded = d["estimator"] == "degraded"
        level = LogLevel.WARNING if degraded else LogLevel.INFO
        code = "ESTIMATOR_DEGRADED" if degraded else "estimator_rearmed"
        message = (f"estimator {d['estimator']} ({d.get('degradations', 0)} so far)"
                   + (f": {FAULT_DESCRIPTIONS['ESTIMATOR_DEGRADED']}" if degraded else ""))
    elif kind == "note" and "stop_contact" in d:
        what = str(d["stop_contact"])
        level = LogLevel.WARNING if what == "degraded" else LogLevel.INFO
        code = f"stop_contact_{what.replace('-', '')}"
        message = (f"bump-stop contact {what}: {d.get('contact_s_in_window', 0.0):.3f} s "
                   "in the window"
                   + (": travel-conservative law until the contact fades"
                      if what == "degraded" else ""))
    else:
        message = _text(detail)
    sec, nsec = divmod(max(int(wall_ns), 0), 1_000_000_000)
    return {"timestamp": {"sec": sec, "nsec": nsec}, "level": int(level),
            "message": _text(message, 1000), "name": kind, "file": code,
            "line": max(int(tick), 0)}


def schema_bytes(schema: dict[str, Any]) -> bytes:
    """The schema as stored in the MCAP Schema record (canonical JSON, UTF-8)."""
    return json.dumps(schema, sort_keys=True, separators=(",", ":")).encode()


def _np_default(obj: Any) -> Any:
    """json ``default``: numpy arrays / scalars -> lists / Python scalars."""
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    if isinstance(obj, bytes | bytearray):
        return obj.hex()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _finite_or(v: Any, fill: float | None) -> tuple[Any, bool]:
    if isinstance(v, float):
        return (v, False) if math.isfinite(v) else (fill, True)
    if isinstance(v, list):
        bad = False
        out = []
        for x in v:
            y, b = _finite_or(x, fill)
            out.append(y)
            bad |= b
        return out, bad
    return v, False


def _encode(obj: dict[str, Any], fill: float | None) -> bytes:
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False,
                          default=_np_default).encode()
    except ValueError:
        plain = json.loads(json.dumps(obj, default=_np_default))  # NaN-tolerant round trip
        bad_keys = []
        for k, v in plain.items():
            plain[k], bad = _finite_or(v, fill)
            if bad:
                bad_keys.append(k)
        plain["nonfinite"] = bad_keys
        return json.dumps(plain, separators=(",", ":"), allow_nan=False).encode()


def encode_json(obj: dict[str, Any]) -> bytes:
    """Compact JSON for the schema-less Zenoh telemetry; non-finite numbers become null
    and their keys are listed in ``nonfinite`` (JSON has no NaN)."""
    return _encode(obj, None)


def encode_message(obj: dict[str, Any]) -> bytes:
    """Compact JSON of one message of a schema'd channel (the recording and the live
    Foxglove view); non-finite numbers become :data:`NONFINITE_NUMBER` and their keys
    are listed in ``nonfinite`` (JSON has no NaN, and the channel schemas allow one type
    per field)."""
    return _encode(obj, NONFINITE_NUMBER)


def event_message(t_ns: int, tick: int, kind: str, detail: Any) -> dict[str, Any]:
    """The ``/rig/events`` message of one event: an unknown ``kind`` becomes ``note`` with
    detail ``{"kind": kind, "detail": detail}``; the detail (object, string or null;
    anything else as its text) is JSON text in ``detail_json``."""
    if kind not in EVENT_KINDS:
        detail, kind = {"kind": str(kind), "detail": detail}, "note"
    if isinstance(detail, Mapping):
        detail = dict(detail)
    elif not (detail is None or isinstance(detail, str)):
        detail = str(detail)
    return {"tick": int(tick), "t_ns": int(t_ns), "kind": kind,
            "detail_json": json.dumps(detail, separators=(",", ":"), default=_np_default)}


def event_from_message(msg: Mapping[str, Any]) -> dict[str, Any]:
    """A decoded ``/rig/events`` message -> ``{"tick", "t_ns", "kind", "detail"}`` (the
    detail decoded from ``detail_json``)."""
    return {"tick": msg["tick"], "t_ns": msg["t_ns"], "kind": msg["kind"],
            "detail": json.loads(msg["detail_json"])}
