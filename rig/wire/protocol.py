"""The rig's CAN protocol: frame IDs, enumerations and a fast codec for ``rig/wire/rig.dbc``.

The DBC is the source of truth and cantools the reference codec.  The codec is generated
from the DBC by ``python -m rig.wire.generate`` into the checked-in
:mod:`rig.wire.dbc_codec` (per frame its frame class and ``encode`` / ``decode`` with the
DBC's bit positions, scales, ranges and ``VAL_`` values written in as literals), next to
:mod:`rig.wire.dbc_constants` (every number as a named constant, the ``VAL_`` tables as
enums, the ``BitFlags`` signals as flag sets such as :class:`SensorStatus`); a test
requires that regenerating changes neither, and ``tests/test_protocol.py``
proves the codec byte-identical to cantools.  The hand-written parts hold no DBC number:
:mod:`rig.wire.codec_base` (decode status, frame and codec base classes), the E2E CRC
tables in :mod:`rig.wire.e2e`, and here the public names.

Hot-path use::

    buf = bytearray(8)                      # e.g. a preallocated can.Message's .data
    mask = VALVE_COMMAND.encode(buf, counter, enable, lifecycle, spool, force_n, echo)
    sd = SensorData()                       # preallocated, mutable, reused every tick
    status = SENSOR_DATA.decode(msg.data, sd)
    if status is DecodeStatus.OK: ... sd.rattlespace_m ...

Encoders write counter (taken modulo 16), signals and the E2E CRC into ``buf``; a
physical value outside its DBC range (or NaN, which encodes as 0) is clamped and
reported in the returned bit mask (bit i = ``FIELDS[i]`` of the frame class; 0 = all
in range); an undefined ``VAL_`` value is sent as it is and flagged; a signal whose DBC
attribute ``CodecOutOfRange`` is ``Wrap`` (FaultTick) is taken modulo its range.
Decoders never raise and never allocate beyond the unpacked tuple: they return a
:class:`DecodeStatus` and fill the output object only when length and CRC are good.
``OUT_OF_RANGE`` means the frame is intact but some raw value lies outside its DBC range
or is not a defined ``VAL_`` value; the fields are filled and ``out.range_mask`` says
which.  Rolling-counter supervision is separate: :class:`rig.wire.e2e.CounterMonitor`.
"""

from __future__ import annotations

from typing import Final

from rig.wire import dbc_constants as K  # noqa: N812  (K: the DBC constants)
from rig.wire.codec_base import Codec, DecodeStatus, Frame, SignalSpec
from rig.wire.dbc_codec import (
    CODECS,
    CONTROLLER_STATUS,
    FAULT_REPORT,
    RIG_STATUS,
    ROAD_PREVIEW,
    SENSOR_DATA,
    VALVE_COMMAND,
    ControllerStatus,
    ControllerStatusCodec,
    FaultReport,
    FaultReportCodec,
    RigStatus,
    RigStatusCodec,
    RoadPreview,
    RoadPreviewCodec,
    SensorData,
    SensorDataCodec,
    ValveCommand,
    ValveCommandCodec,
)
from rig.wire.dbc_constants import (
    Blending,
    FaultCode,
    LifecycleState,
    PreviewStatus,
    SensorStatus,
)
from rig.wire.e2e import CounterMonitor, CounterStatus

__all__ = [
    "CODECS",
    "CONTROLLER_RX_IDS",
    "CONTROLLER_STATUS",
    "CONTROLLER_STATUS_ID",
    "FAULT_REPORT",
    "FAULT_REPORT_ID",
    "FRAME_LENGTH",
    "RIG_RX_IDS",
    "RIG_STATUS",
    "RIG_STATUS_ID",
    "ROAD_PREVIEW",
    "ROAD_PREVIEW_ID",
    "SENSOR_DATA",
    "SENSOR_DATA_ID",
    "VALVE_COMMAND",
    "VALVE_COMMAND_ID",
    "Blending",
    "Codec",
    "ControllerStatus",
    "ControllerStatusCodec",
    "CounterMonitor",
    "CounterStatus",
    "DecodeStatus",
    "FaultCode",
    "FaultReport",
    "FaultReportCodec",
    "Frame",
    "LifecycleState",
    "PreviewStatus",
    "RigStatus",
    "RigStatusCodec",
    "RoadPreview",
    "RoadPreviewCodec",
    "SensorData",
    "SensorDataCodec",
    "SensorStatus",
    "SignalSpec",
    "ValveCommand",
    "ValveCommandCodec",
]

FRAME_LENGTH: Final = K.VALVE_COMMAND_LENGTH
VALVE_COMMAND_ID: Final = K.VALVE_COMMAND_ID
FAULT_REPORT_ID: Final = K.FAULT_REPORT_ID
SENSOR_DATA_ID: Final = K.SENSOR_DATA_ID
RIG_STATUS_ID: Final = K.RIG_STATUS_ID
ROAD_PREVIEW_ID: Final = K.ROAD_PREVIEW_ID
CONTROLLER_STATUS_ID: Final = K.CONTROLLER_STATUS_ID
#: frames each role receives (receive filters of :func:`rig.bus.core.open_bus`)
CONTROLLER_RX_IDS: Final = (SENSOR_DATA_ID, ROAD_PREVIEW_ID, RIG_STATUS_ID)
RIG_RX_IDS: Final = (VALVE_COMMAND_ID, FAULT_REPORT_ID, CONTROLLER_STATUS_ID)


