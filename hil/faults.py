"""Scriptable fault injection for the emulated rig's CAN node (:class:`hil.node.RigNode`).

A :class:`FaultSchedule` is a list of time windows ``[start_s, end_s)`` (rig time, i.e.
tick x dt, so tick-stepped tests are exact), each with a fault kind and parameters, plus
a seed for the random ones.  Kinds (``frames`` selects "sensor" = SensorData, "status" =
RigStatus, "preview" = RoadPreview or "all"; default "sensor"):

==================  ==============================================  =====================
kind                effect on the bus / rig                          params (default)
==================  ==============================================  =====================
``drop``            frames not sent, each with ``probability``       probability (1.0),
                                                                     frames
``delay``           frames held ``ticks`` ticks, then sent (late)    ticks (5), frames
``corrupt_crc``     byte 0 XOR ``xor``: the E2E CRC check fails       xor (0x5A), frames
``stuck_counter``   rolling counter does not advance                 frames
``frozen_sensor``   SensorData repeats the values sent last          --
``out_of_range``    sensor values replaced by ``value`` (clamped by   signal ("all":
                    the codec to the DBC limit: beyond sensor range)  rattlespace, force,
                                                                     accel), value (1e9)
``sensor_status``   SensorStatus bits set (sensor self-diagnosis)    bits (1 = LVDT)
``silence``         the node transmits nothing                       --
``supply_loss``     hydraulic supply pressure lost (SupplyOk = 0)    --
==================  ==============================================  =====================

Files (``FaultSchedule.load``): TOML or JSON::

    seed = 7
    [[faults]]
    kind = "stuck_counter"
    start_s = 1.0
    end_s = 1.2

JSON may also be a plain list of ``[start_s, end_s, kind, {params}]``.  Every entry is
validated; errors raise :class:`controller.config.ConfigError` naming the entry and key.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from controller.config import ConfigError, parse_toml, read_text_file

__all__ = ["FaultKind", "FaultSchedule", "FaultWindow"]


class FaultKind(StrEnum):
    DROP = "drop"
    DELAY = "delay"
    CORRUPT_CRC = "corrupt_crc"
    STUCK_COUNTER = "stuck_counter"
    FROZEN_SENSOR = "frozen_sensor"
    OUT_OF_RANGE = "out_of_range"
    SENSOR_STATUS = "sensor_status"
    SILENCE = "silence"
    SUPPLY_LOSS = "supply_loss"


_FRAMES = ("sensor", "status", "preview", "all")
_SIGNALS = ("rattlespace", "force", "accel", "all")
#: kind -> {param: (default, validator description, check)}
_PARAMS: dict[FaultKind, dict[str, Any]] = {
    FaultKind.DROP: {"probability": 1.0, "frames": "sensor"},
    FaultKind.DELAY: {"ticks": 5, "frames": "sensor"},
    FaultKind.CORRUPT_CRC: {"xor": 0x5A, "frames": "sensor"},
    FaultKind.STUCK_COUNTER: {"frames": "sensor"},
    FaultKind.FROZEN_SENSOR: {},
    FaultKind.OUT_OF_RANGE: {"signal": "all", "value": 1e9},
    FaultKind.SENSOR_STATUS: {"bits": 1},
    FaultKind.SILENCE: {},
    FaultKind.SUPPLY_LOSS: {},
}


def _check_param(key: str, kind: FaultKind, name: str, value: Any) -> Any:
    if name == "frames":
        if value not in _FRAMES:
            raise ConfigError(key, value, f"one of {_FRAMES}")
        return value
    if name == "signal":
        if value not in _SIGNALS:
            raise ConfigError(key, value, f"one of {_SIGNALS}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(key, value, "a number")
    if name == "probability":
        if not 0.0 <= value <= 1.0:
            raise ConfigError(key, value, "[0, 1]")
        return float(value)
    if name == "ticks":
        if not isinstance(value, int) or not 1 <= value <= 100_000:
            raise ConfigError(key, value, "an integer in [1, 100000]")
        return value
    if name == "xor":
        if not isinstance(value, int) or not 1 <= value <= 255:
            raise ConfigError(key, value, "an integer in [1, 255] (0 would not corrupt)")
        return value
    if name == "bits":
        if not isinstance(value, int) or not 1 <= value <= 15:
            raise ConfigError(key, value, "an integer in [1, 15]")
        return value
    if name == "value":
        if math.isnan(value):
            raise ConfigError(key, value, "a number (inf allowed, not NaN)")
        return float(value)
    raise ConfigError(key, value, f"a parameter of {kind.value}")  # pragma: no cover


@dataclass(frozen=True)
class FaultWindow:
    """One scripted fault, active for rig time ``start_s <= t < end_s``."""

    start_s: float
    end_s: float
    kind: FaultKind
    params: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def build(cls, start_s: Any, end_s: Any, kind: Any, params: Mapping[str, Any] | None,
              where: str = "fault") -> FaultWindow:
        """Validated window; fills parameter defaults."""
        for name, t in (("start_s", start_s), ("end_s", end_s)):
            if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t) \
                    or t < 0:
                raise ConfigError(f"{where}.{name}", t, "a finite time >= 0 [s]")
        if end_s <= start_s:
            raise ConfigError(f"{where}.end_s", end_s, f"> start_s = {start_s}")
        try:
            fk = FaultKind(kind)
        except ValueError:
            raise ConfigError(f"{where}.kind", kind,
                              f"one of {[k.value for k in FaultKind]}") from None
        allowed = _PARAMS[fk]
        given = dict(params or {})
        for name in given:
            if name not in allowed:
                raise ConfigError(f"{where}.{name}", given[name],
                                  f"a parameter of {fk.value}: {sorted(allowed) or 'none'}")
        merged = {name: _check_param(f"{where}.{name}", fk, name, given.get(name, default))
                  for name, default in allowed.items()}
        return cls(float(start_s), float(end_s), fk, merged)

    def hits(self, frame: str) -> bool:
        """Whether this window acts on ``frame`` ("sensor", "status" or "preview")."""
        target = self.params.get("frames", "sensor")
        return bool(target == "all" or target == frame)


def _parse_json(text: str, path: Path) -> Any:
    """``json.loads`` without NaN / Infinity, errors as :class:`ConfigError`."""
    def no_constant(name: str) -> Any:
        raise ValueError(f"{name} is not a number")

    try:
        return json.loads(text, parse_constant=no_constant)
    except ValueError as exc:   # json.JSONDecodeError is a ValueError
        raise ConfigError("<file>", str(path), f"valid JSON ({exc})") from exc
    except RecursionError:
        raise ConfigError("<file>", str(path),
                          "valid JSON nested at most a few hundred levels deep") from None


class FaultSchedule:
    """Faults by time, deterministic for a seed.  Empty schedule = no faults."""

    def __init__(self, windows: Iterable[FaultWindow] = (), seed: int = 0) -> None:
        self.windows: tuple[FaultWindow, ...] = tuple(
            sorted(windows, key=lambda w: (w.start_s, w.end_s)))
        self.seed = int(seed)
        self._ticks: list[tuple[int, int, FaultWindow]] = []
        self._dt_s = 0.0

    def __len__(self) -> int:
        return len(self.windows)

    def __repr__(self) -> str:
        return f"FaultSchedule({list(self.windows)!r}, seed={self.seed})"

    @classmethod
    def from_list(cls, entries: Sequence[Any], seed: int = 0) -> FaultSchedule:
        """From ``[(start_s, end_s, kind, params), ...]`` or a list of mappings with
        ``start_s``, ``end_s``, ``kind`` and the parameters as further keys."""
        windows = []
        for i, entry in enumerate(entries):
            where = f"faults[{i}]"
            if isinstance(entry, Mapping):
                rest = {k: v for k, v in entry.items() if k not in ("start_s", "end_s", "kind")}
                for key in ("start_s", "end_s", "kind"):
                    if key not in entry:
                        raise ConfigError(f"{where}.{key}", None, "present")
                windows.append(FaultWindow.build(entry["start_s"], entry["end_s"],
                                                 entry["kind"], rest, where))
            elif isinstance(entry, Sequence) and not isinstance(entry, str) \
                    and len(entry) in (3, 4):
                params = entry[3] if len(entry) == 4 else {}
                if not isinstance(params, Mapping):
                    raise ConfigError(f"{where}[3]", params, "a table of parameters")
                windows.append(FaultWindow.build(entry[0], entry[1], entry[2], params, where))
            else:
                raise ConfigError(where, entry,
                                  "[start_s, end_s, kind, {params}] or a table")
        return cls(windows, seed)

    @classmethod
    def from_mapping(cls, data: Any) -> FaultSchedule:
        if isinstance(data, list):
            return cls.from_list(data)
        if not isinstance(data, Mapping):
            raise ConfigError("<faults file>", type(data).__name__, "a table or a list")
        unknown = set(data) - {"seed", "faults"}
        if unknown:
            key = sorted(unknown)[0]
            raise ConfigError(key, data[key], "'seed' or 'faults'")
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError("seed", seed, "an integer >= 0")
        entries = data.get("faults", [])
        if not isinstance(entries, list):
            raise ConfigError("faults", entries, "a list of fault tables")
        return cls.from_list(entries, seed)

    @classmethod
    def load(cls, path: str | Path) -> FaultSchedule:
        """Read a ``.toml`` or ``.json`` schedule (by suffix; else TOML, then JSON)."""
        p = Path(path)
        suffix = p.suffix.lower()
        text = read_text_file(p, {".json": "JSON", ".toml": "TOML"}.get(suffix, "TOML or JSON"))
        if suffix == ".json":
            return cls.from_mapping(_parse_json(text, p))
        try:
            return cls.from_mapping(parse_toml(text, p))
        except ConfigError as exc:
            if suffix == ".toml" or exc.key != "<file>":
                raise
        try:
            return cls.from_mapping(_parse_json(text, p))
        except ConfigError as exc:
            raise ConfigError("<file>", str(p), "valid TOML or JSON") from exc

    def bind(self, dt_s: float) -> None:
        """Convert the windows to tick ranges ``[round(start/dt), round(end/dt))``."""
        self._dt_s = dt_s
        self._ticks = [(round(w.start_s / dt_s), round(w.end_s / dt_s), w)
                       for w in self.windows]

    def active(self, tick: int) -> list[FaultWindow]:
        """Windows active at ``tick`` (after :meth:`bind`); empty list when none."""
        return [w for t0, t1, w in self._ticks if t0 <= tick < t1]

    @property
    def end_s(self) -> float:
        return max((w.end_s for w in self.windows), default=0.0)
