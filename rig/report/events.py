"""The recording's ``/rig/events`` as table rows: time, code and a plain-language reason.

The reason of a fault is the fault code's own description
(:attr:`rig.wire.protocol.FaultCode.description`); lifecycle transitions and operator
commands carry their reason / message in the event (docs/recording.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from rig.report.series import RunSeries
from rig.wire.protocol import FaultCode

__all__ = ["EventRow", "event_rows"]

_DETAILS_CHARS = 300


@dataclass(frozen=True)
class EventRow:
    number: int        # 1-based, also the marker on the lifecycle plot
    t_s: float         # seconds since the first tick
    tick: int
    kind: str          # command, lifecycle, fault, note
    change: str        # "INACTIVE → FAULT" for a transition, else ""
    code: str          # fault code, command name, or what a note is about
    reason: str        # plain language
    details: str       # the event's own message / remaining fields


def _compact(v: Any) -> str:
    text = v if isinstance(v, str) else json.dumps(v, separators=(", ", ": "), default=str)
    return text if len(text) <= _DETAILS_CHARS else text[:_DETAILS_CHARS - 1] + "…"


def fault_description(name: str) -> str:
    """The description of fault code ``name`` (or say that it is unknown)."""
    try:
        return FaultCode[name].description
    except KeyError:
        return f"Fault code {name} is not known to this version."


def _row(n: int, t_s: float, tick: int, kind: str, d: Any) -> EventRow:
    if kind in ("fault", "lifecycle") and isinstance(d, dict):
        change = f"{d.get('from', '?')} → {d.get('to', '?')}"
        reason = str(d.get("reason", ""))
        code = str(d.get("fault", "NONE"))
        if kind == "fault":
            prefix = f"fault {code}: "
            details = reason[len(prefix):] if reason.startswith(prefix) else reason
            return EventRow(n, t_s, tick, kind, change, code, fault_description(code),
                            _compact(details))
        return EventRow(n, t_s, tick, kind, change, "" if code == "NONE" else code,
                        reason, "")
    if kind == "command" and isinstance(d, dict):
        name = str(d.get("command", "?"))
        arg = d.get("argument")
        code = name if arg is None else f"{name} {arg}"
        accepted = bool(d.get("accepted"))
        return EventRow(n, t_s, tick, kind, "", code, str(d.get("message", "")),
                        "accepted" if accepted else f"refused (state {d.get('state', '?')})")
    if isinstance(d, dict):
        if "bus_exception" in d:
            return EventRow(n, t_s, tick, kind, "", f"bus {d['bus_exception']}",
                            f"{d.get('type', '')}: {d.get('error', '')}",
                            _compact({k: v for k, v in d.items()
                                      if k not in ("bus_exception", "type", "error")}))
        return EventRow(n, t_s, tick, kind, "", str(d.get("kind", "")), "", _compact(d))
    return EventRow(n, t_s, tick, kind, "", "", "" if d is None else _compact(d), "")


def event_rows(s: RunSeries) -> list[EventRow]:
    """Every event of the recording, in recording order."""
    return [_row(i + 1, s.event_time_s(e), int(e.get("tick", -1)), str(e.get("kind", "")),
                 e.get("detail")) for i, e in enumerate(s.events)]
