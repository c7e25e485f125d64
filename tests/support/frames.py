"""Reading frames of the protocol in tests: what the controller sent on a python-can bus
(:func:`drain_controller_frames`), any frame by ID (:class:`FrameDecoder`)."""

from __future__ import annotations

from typing import Any, Final

import can

from rig.wire.protocol import (
    CODECS,
    CONTROLLER_STATUS,
    CONTROLLER_STATUS_ID,
    FAULT_REPORT,
    FAULT_REPORT_ID,
    RIG_STATUS_ID,
    SENSOR_DATA_ID,
    VALVE_COMMAND,
    VALVE_COMMAND_ID,
    ControllerStatus,
    DecodeStatus,
    FaultReport,
    Frame,
    RigStatus,
    SensorData,
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


_UNKNOWN_ID: Final = DecodeStatus.UNKNOWN_ID


class FrameDecoder:
    """Decode any frame of the protocol by ID into preallocated per-ID objects.

    ``status = dec.decode(msg.arbitration_id, msg.data)``; on OK / OUT_OF_RANGE the
    values are in ``dec.frames[frame_id]`` (also ``dec.sensor_data`` etc.).  Unknown IDs
    (and extended IDs: pass ``is_extended=True``) give UNKNOWN_ID.  Never raises for a
    bytes-like payload of any length.
    """

    def __init__(self) -> None:
        # every frame of the DBC (CODECS owns the list: a frame added there is decoded)
        self.frames: dict[int, Frame] = {fid: codec.new() for fid, codec in CODECS.items()}
        self._dispatch: dict[int, tuple[Any, Frame]] = {
            fid: (CODECS[fid], frame) for fid, frame in self.frames.items()
        }
        self.valve_command: ValveCommand = self.frames[VALVE_COMMAND_ID]  # type: ignore[assignment]
        self.fault_report: FaultReport = self.frames[FAULT_REPORT_ID]  # type: ignore[assignment]
        self.sensor_data: SensorData = self.frames[SENSOR_DATA_ID]  # type: ignore[assignment]
        self.rig_status: RigStatus = self.frames[RIG_STATUS_ID]  # type: ignore[assignment]
        self.controller_status: ControllerStatus = \
            self.frames[CONTROLLER_STATUS_ID]  # type: ignore[assignment]

    def decode(self, frame_id: int, data: bytes | bytearray | memoryview,
               is_extended: bool = False) -> DecodeStatus:
        entry = None if is_extended else self._dispatch.get(frame_id)
        if entry is None:
            return _UNKNOWN_ID
        codec, frame = entry
        status: DecodeStatus = codec.decode(data, frame)
        return status
