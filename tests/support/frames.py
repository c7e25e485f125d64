"""Reading what the controller sent, frame by frame, on a python-can bus."""

from __future__ import annotations

import can

from rig.wire.protocol import (
    CONTROLLER_STATUS,
    CONTROLLER_STATUS_ID,
    FAULT_REPORT,
    FAULT_REPORT_ID,
    VALVE_COMMAND,
    VALVE_COMMAND_ID,
    ControllerStatus,
    FaultReport,
    ValveCommand,
)


def drain_controller_frames(
        bus: can.BusABC, strict: bool = True,
) -> tuple[list[ValveCommand], list[FaultReport], list[ControllerStatus]]:
    """Decode every frame waiting on ``bus`` (without blocking) into the valve
    commands, fault reports and status heartbeats the controller sent.  With
    ``strict`` each must decode OK (an assertion names the frame)."""
    valves: list[ValveCommand] = []
    faults: list[FaultReport] = []
    status: list[ControllerStatus] = []
    codecs = {VALVE_COMMAND_ID: (VALVE_COMMAND, ValveCommand, valves),
              FAULT_REPORT_ID: (FAULT_REPORT, FaultReport, faults),
              CONTROLLER_STATUS_ID: (CONTROLLER_STATUS, ControllerStatus, status)}
    while (msg := bus.recv(0.0)) is not None:
        entry = codecs.get(msg.arbitration_id)
        if entry is None:
            continue
        codec, frame_type, out = entry
        frame = frame_type()
        result = codec.decode(msg.data, frame)
        assert not strict or result.name == "OK", (codec.NAME, result.name)
        out.append(frame)   # type: ignore[arg-type]
    return valves, faults, status
