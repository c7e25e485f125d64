"""Analysis of a candump capture of a rig <-> service run, decoded with cantools.

Independent of the project's codec: the DBC and cantools decode, ``support.frame_crc``
checks the E2E CRC.  Timestamps are candump's (kernel receive time of the capturing
socket, seconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import cantools
import numpy as np

from tests.socketcan.support import DBC_PATH, CapturedFrame, frame_crc

SENSOR_DATA, RIG_STATUS, VALVE_COMMAND = 0x100, 0x200, 0x080
FAULT_REPORT, CONTROLLER_STATUS = 0x081, 0x300
CAN_ERR_FLAG = 0x20000000


@cache
def database() -> Any:
    return cantools.database.load_file(str(DBC_PATH))


@dataclass
class Decoded:
    t_s: float
    frame_id: int
    data: bytes
    crc_ok: bool
    counter: int
    signals: dict[str, Any] = field(default_factory=dict)


def decode_all(frames: list[CapturedFrame]) -> list[Decoded]:
    """Every data frame of a known ID, decoded (choices as strings); error frames kept
    with empty signals and ``frame_id`` including ``CAN_ERR_FLAG``."""
    db = database()
    known = {m.frame_id for m in db.messages}
    out = []
    for f in frames:
        fid = f.arbitration_id
        if fid in known and len(f.data) == 8:
            sig = db.decode_message(fid, f.data, decode_choices=True)
            out.append(Decoded(f.timestamp_s, fid, f.data, f.data[0] == frame_crc(fid, f.data),
                               f.data[1] & 0x0F, dict(sig)))
        elif fid & CAN_ERR_FLAG or len(f.data) != 8 or fid not in known:
            out.append(Decoded(f.timestamp_s, fid, f.data, False, -1, {}))
    return out


def of(frames: list[Decoded], frame_id: int) -> list[Decoded]:
    return [f for f in frames if f.frame_id == frame_id]


def enable(f: Decoded) -> int:
    return int(f.signals["Enable"])


def first_armed_time(frames: list[Decoded]) -> float | None:
    """Capture time of the first ValveCommand with Enable = 1."""
    return next((f.t_s for f in of(frames, VALVE_COMMAND) if enable(f)), None)


@dataclass(frozen=True)
class Reaction:
    """The service's reaction to a fault that became observable at ``t_observable_s``."""

    t_observable_s: float
    t_safe_s: float | None          # first ValveCommand Enable=0 at/after t_observable
    enabled_after: int              # ValveCommands with Enable=1 sent after t_observable
    t_report_s: float | None        # first FaultReport at/after t_observable
    fault_code: str | None          # its FaultCode (choice name)

    @property
    def reaction_s(self) -> float:
        return math.nan if self.t_safe_s is None else self.t_safe_s - self.t_observable_s


def reaction(frames: list[Decoded], t_observable_s: float) -> Reaction:
    valves = [f for f in of(frames, VALVE_COMMAND) if f.t_s >= t_observable_s]
    safe = next((f for f in valves if not enable(f)), None)
    enabled_after = sum(1 for f in valves if enable(f) and (safe is None or f.t_s < safe.t_s))
    report = next((f for f in of(frames, FAULT_REPORT) if f.t_s >= t_observable_s), None)
    return Reaction(t_observable_s, safe.t_s if safe else None, enabled_after,
                    report.t_s if report else None,
                    str(report.signals["FaultCode"]) if report else None)


def sensor_to_command_latency_s(frames: list[Decoded]) -> np.ndarray:
    """For each ValveCommand: time since the SensorData frame whose counter it echoes
    (the latest such frame before it)."""
    last_by_counter: dict[int, float] = {}
    out = []
    for f in frames:
        if f.frame_id == SENSOR_DATA and f.crc_ok:
            last_by_counter[f.counter] = f.t_s
        elif f.frame_id == VALVE_COMMAND:
            t = last_by_counter.get(int(f.signals["SensorCounterEcho"]))
            if t is not None:
                out.append(f.t_s - t)
    return np.asarray(out)


def period_stats_s(times: list[float]) -> dict[str, float]:
    """Inter-frame interval statistics of a periodic frame (its jitter on the bus)."""
    d = np.diff(np.asarray(times))
    if d.size == 0:
        return {"n": 0}
    return {"n": float(d.size), "median": float(np.median(d)),
            "p01": float(np.percentile(d, 1)), "p99": float(np.percentile(d, 99)),
            "max": float(d.max())}


def command_delay_ticks(frames: list[Decoded]) -> np.ndarray:
    """Per ValveCommand, the loop delay in the offline simulator's terms (``delay_ticks``
    of ``hil.sim.closed_loop.simulate``): the number of SensorData frames sent between the frame the
    command echoes and the command.  The rig applies a command at its next tick, so 0 =
    the command is applied in the tick right after the reading it was computed from."""
    out = []
    last_index_by_counter: dict[int, int] = {}
    n_sd = 0
    for f in frames:
        if f.frame_id == SENSOR_DATA and f.crc_ok:
            last_index_by_counter[f.counter] = n_sd
            n_sd += 1
        elif f.frame_id == VALVE_COMMAND and enable(f):
            k = last_index_by_counter.get(int(f.signals["SensorCounterEcho"]))
            if k is not None:
                out.append(n_sd - 1 - k)
    return np.asarray(out, dtype=int)
