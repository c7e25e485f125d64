"""The rig's CAN protocol: frame IDs, enumerations and a fast codec for ``rig/wire/rig.dbc``.

The DBC is the source of truth and cantools the reference codec.  Every number of the
protocol (IDs, bit positions, scales, ranges, ``VAL_`` tables, the ``struct`` layouts)
comes from :mod:`rig.wire.dbc_constants`, generated from the DBC by
``python -m rig.wire.generate`` (a test requires that regenerating changes nothing); this
module adds the hand-optimised encode/decode functions over those constants and the
precomputed CRC tables, proven byte-identical to cantools by ``tests/test_protocol.py``.
Hot-path use::

    buf = bytearray(8)                      # e.g. a preallocated can.Message's .data
    mask = VALVE_COMMAND.encode(buf, counter, enable, lifecycle, spool, force_n, echo)
    sd = SensorData()                       # preallocated, mutable, reused every tick
    status = SENSOR_DATA.decode(msg.data, sd)
    if status is DecodeStatus.OK: ... sd.rattlespace_m ...

Encoders write counter (taken modulo 16), signals and the E2E CRC into ``buf``; a
physical value outside its DBC range (or NaN, which encodes as 0) is clamped and
reported in the returned bit mask (bit i = ``codec.FIELDS[i]``; 0 = all in range).
Decoders never raise and never allocate beyond the unpacked tuple: they return a
:class:`DecodeStatus` and fill the output object only when length and CRC are good.
``OUT_OF_RANGE`` means the frame is intact but some raw value lies outside its DBC range
or is not a defined ``VAL_`` value; the fields are filled and ``out.range_mask`` says
which.  Rolling-counter supervision is separate: :class:`rig.wire.e2e.CounterMonitor`.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from enum import IntEnum, IntFlag
from typing import Any, ClassVar, Final, NamedTuple

from rig.wire import dbc_constants as K  # noqa: N812  (K: the DBC constants)
from rig.wire.dbc_constants import (
    CONTROLLER_STATUS_ACTIVE_FAULT_MAX,
    CONTROLLER_STATUS_ACTIVE_FAULT_MIN,
    CONTROLLER_STATUS_ACTIVE_FAULT_VALUES,
    CONTROLLER_STATUS_BLENDING_MASK,
    CONTROLLER_STATUS_BLENDING_MAX,
    CONTROLLER_STATUS_BLENDING_MIN,
    CONTROLLER_STATUS_BLENDING_SHIFT,
    CONTROLLER_STATUS_BLENDING_VALUES,
    CONTROLLER_STATUS_COUNTER_MASK,
    CONTROLLER_STATUS_COUNTER_SIGNAL,
    CONTROLLER_STATUS_JITTER_P99_MAX,
    CONTROLLER_STATUS_JITTER_P99_MIN,
    CONTROLLER_STATUS_JITTER_P99_SCALE,
    CONTROLLER_STATUS_LENGTH,
    CONTROLLER_STATUS_NAME,
    CONTROLLER_STATUS_OVERRUN_COUNT_MAX,
    CONTROLLER_STATUS_OVERRUN_COUNT_MIN,
    CONTROLLER_STATUS_STATE_MASK,
    CONTROLLER_STATUS_STATE_MAX,
    CONTROLLER_STATUS_STATE_MIN,
    CONTROLLER_STATUS_STATE_SHIFT,
    CONTROLLER_STATUS_STATE_VALUES,
    CONTROLLER_STATUS_STRUCT,
    CONTROLLER_STATUS_WEIGHT_SET_MASK,
    CONTROLLER_STATUS_WEIGHT_SET_MAX,
    CONTROLLER_STATUS_WEIGHT_SET_MIN,
    CONTROLLER_STATUS_WEIGHT_SET_SHIFT,
    FAULT_REPORT_COUNTER_MASK,
    FAULT_REPORT_COUNTER_SIGNAL,
    FAULT_REPORT_FAULT_CODE_MAX,
    FAULT_REPORT_FAULT_CODE_MIN,
    FAULT_REPORT_FAULT_CODE_VALUES,
    FAULT_REPORT_FAULT_DETAIL_MAX,
    FAULT_REPORT_FAULT_DETAIL_MIN,
    FAULT_REPORT_FAULT_STATE_MASK,
    FAULT_REPORT_FAULT_STATE_MAX,
    FAULT_REPORT_FAULT_STATE_MIN,
    FAULT_REPORT_FAULT_STATE_SHIFT,
    FAULT_REPORT_FAULT_STATE_VALUES,
    FAULT_REPORT_FAULT_TICK_RAW_MAX,
    FAULT_REPORT_LENGTH,
    FAULT_REPORT_NAME,
    FAULT_REPORT_STRUCT,
    RIG_STATUS_BYPASS_OPEN_MASK,
    RIG_STATUS_BYPASS_OPEN_SHIFT,
    RIG_STATUS_COUNTER_MASK,
    RIG_STATUS_COUNTER_SIGNAL,
    RIG_STATUS_LENGTH,
    RIG_STATUS_LOAD_PRESSURE_MAX,
    RIG_STATUS_LOAD_PRESSURE_MIN,
    RIG_STATUS_LOAD_PRESSURE_SCALE,
    RIG_STATUS_NAME,
    RIG_STATUS_SPOOL_POSITION_MAX,
    RIG_STATUS_SPOOL_POSITION_MIN,
    RIG_STATUS_SPOOL_POSITION_RAW_MAX,
    RIG_STATUS_SPOOL_POSITION_RAW_MIN,
    RIG_STATUS_SPOOL_POSITION_SCALE,
    RIG_STATUS_STRUCT,
    RIG_STATUS_SUPPLY_OK_MASK,
    RIG_STATUS_SUPPLY_OK_SHIFT,
    RIG_STATUS_SUPPLY_PRESSURE_MAX,
    RIG_STATUS_SUPPLY_PRESSURE_MIN,
    RIG_STATUS_SUPPLY_PRESSURE_SCALE,
    RIG_STATUS_WATCHDOG_TRIPPED_MASK,
    RIG_STATUS_WATCHDOG_TRIPPED_SHIFT,
    SENSOR_DATA_COUNTER_MASK,
    SENSOR_DATA_COUNTER_SIGNAL,
    SENSOR_DATA_LENGTH,
    SENSOR_DATA_LOAD_CELL_FORCE_MAX,
    SENSOR_DATA_LOAD_CELL_FORCE_MIN,
    SENSOR_DATA_LOAD_CELL_FORCE_SCALE,
    SENSOR_DATA_NAME,
    SENSOR_DATA_RATTLESPACE_MAX,
    SENSOR_DATA_RATTLESPACE_MIN,
    SENSOR_DATA_RATTLESPACE_SCALE,
    SENSOR_DATA_SENSOR_STATUS_MASK,
    SENSOR_DATA_SENSOR_STATUS_MAX,
    SENSOR_DATA_SENSOR_STATUS_MIN,
    SENSOR_DATA_SENSOR_STATUS_SHIFT,
    SENSOR_DATA_SPRUNG_ACCEL_MAX,
    SENSOR_DATA_SPRUNG_ACCEL_MIN,
    SENSOR_DATA_SPRUNG_ACCEL_SCALE,
    SENSOR_DATA_STRUCT,
    VALVE_COMMAND_COUNTER_MASK,
    VALVE_COMMAND_COUNTER_SIGNAL,
    VALVE_COMMAND_ENABLE_MASK,
    VALVE_COMMAND_ENABLE_SHIFT,
    VALVE_COMMAND_FORCE_REFERENCE_MAX,
    VALVE_COMMAND_FORCE_REFERENCE_MIN,
    VALVE_COMMAND_FORCE_REFERENCE_SCALE,
    VALVE_COMMAND_LENGTH,
    VALVE_COMMAND_LIFECYCLE_MASK,
    VALVE_COMMAND_LIFECYCLE_MAX,
    VALVE_COMMAND_LIFECYCLE_MIN,
    VALVE_COMMAND_LIFECYCLE_SHIFT,
    VALVE_COMMAND_LIFECYCLE_VALUES,
    VALVE_COMMAND_NAME,
    VALVE_COMMAND_SENSOR_COUNTER_ECHO_MASK,
    VALVE_COMMAND_SENSOR_COUNTER_ECHO_MAX,
    VALVE_COMMAND_SENSOR_COUNTER_ECHO_MIN,
    VALVE_COMMAND_SENSOR_COUNTER_ECHO_SHIFT,
    VALVE_COMMAND_SPOOL_COMMAND_MAX,
    VALVE_COMMAND_SPOOL_COMMAND_MIN,
    VALVE_COMMAND_SPOOL_COMMAND_RAW_MAX,
    VALVE_COMMAND_SPOOL_COMMAND_RAW_MIN,
    VALVE_COMMAND_SPOOL_COMMAND_SCALE,
    VALVE_COMMAND_STRUCT,
    Blending,
    FaultCode,
    LifecycleState,
)
from rig.wire.e2e import CRC8_TABLE, CRC8_TABLE2, CounterMonitor, CounterStatus, frame_crc_start

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
    "SENSOR_DATA",
    "SENSOR_DATA_ID",
    "VALVE_COMMAND",
    "VALVE_COMMAND_ID",
    "Blending",
    "ControllerStatus",
    "ControllerStatusCodec",
    "CounterMonitor",
    "CounterStatus",
    "DecodeStatus",
    "FaultCode",
    "FaultReport",
    "FaultReportCodec",
    "FrameDecoder",
    "LifecycleState",
    "RigStatus",
    "RigStatusCodec",
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
CONTROLLER_STATUS_ID: Final = K.CONTROLLER_STATUS_ID
#: frames each role receives (receive filters of :func:`rig.bus.core.open_bus`)
CONTROLLER_RX_IDS: Final = (SENSOR_DATA_ID, RIG_STATUS_ID)
RIG_RX_IDS: Final = (VALVE_COMMAND_ID, FAULT_REPORT_ID, CONTROLLER_STATUS_ID)


class SensorStatus(IntFlag):
    """``SensorData.SensorStatus`` bits (a set bit = that sensor reports a fault)."""

    LVDT_FAULT = 1
    LOAD_CELL_FAULT = 2
    ACCEL_FAULT = 4


class DecodeStatus(IntEnum):
    OK = 0
    BAD_LENGTH = 1  #: payload is not exactly 8 bytes
    UNKNOWN_ID = 2  #: not a frame of this protocol (FrameDecoder only)
    BAD_CRC = 3  #: E2E CRC mismatch: corrupted frame or wrong data ID
    OUT_OF_RANGE = 4  #: intact, fields filled, some value outside DBC range (range_mask)


class SignalSpec(NamedTuple):
    """One DBC signal as this codec sees it (checked against cantools by the tests)."""

    attr: str  #: attribute of the frame object
    dbc_name: str
    start_bit: int
    length: int
    signed: bool
    scale: float
    minimum: float
    maximum: float
    choices: tuple[int, ...] | None = None  #: defined VAL_ values, if any


_OK, _BAD_LENGTH, _UNKNOWN_ID, _BAD_CRC, _OUT_OF_RANGE = (
    DecodeStatus.OK, DecodeStatus.BAD_LENGTH, DecodeStatus.UNKNOWN_ID, DecodeStatus.BAD_CRC,
    DecodeStatus.OUT_OF_RANGE,
)
_WORDS: Final = struct.Struct(">xHHHB")
_T1: Final = CRC8_TABLE
_T2: Final = CRC8_TABLE2


def _specs(frame: str) -> tuple[SignalSpec, ...]:
    """The frame's signals (counter and CRC apart) as :class:`SignalSpec`, from the
    generated :mod:`rig.wire.dbc_constants`."""
    out = []
    for stem in getattr(K, f"{frame}_SIGNALS"):
        def get(what: str, default: Any = None, _p: str = f"{frame}_{stem}_") -> Any:
            return getattr(K, _p + what, default)
        values = get("VALUES")
        out.append(SignalSpec(get("ATTR"), get("DBC"), get("START"), get("LENGTH"),
                              get("SIGNED"), get("SCALE"), get("MIN"), get("MAX"),
                              None if values is None else tuple(sorted(values))))
    return tuple(out)


def _bit(frame: str, stem: str) -> int:
    """The bit of a signal in the encoders' clamp mask and ``range_mask`` (its position
    among the frame's signals, as in the frame object's FIELDS)."""
    return 1 << getattr(K, f"{frame}_SIGNALS").index(stem)


_VC_LIFECYCLE_BIT: Final = _bit("VALVE_COMMAND", "LIFECYCLE")
_VC_SPOOL_COMMAND_BIT: Final = _bit("VALVE_COMMAND", "SPOOL_COMMAND")
_VC_FORCE_REFERENCE_BIT: Final = _bit("VALVE_COMMAND", "FORCE_REFERENCE")
_VC_SENSOR_COUNTER_ECHO_BIT: Final = _bit("VALVE_COMMAND", "SENSOR_COUNTER_ECHO")
_FR_FAULT_STATE_BIT: Final = _bit("FAULT_REPORT", "FAULT_STATE")
_FR_FAULT_CODE_BIT: Final = _bit("FAULT_REPORT", "FAULT_CODE")
_FR_FAULT_DETAIL_BIT: Final = _bit("FAULT_REPORT", "FAULT_DETAIL")
_SD_SENSOR_STATUS_BIT: Final = _bit("SENSOR_DATA", "SENSOR_STATUS")
_SD_RATTLESPACE_BIT: Final = _bit("SENSOR_DATA", "RATTLESPACE")
_SD_LOAD_CELL_FORCE_BIT: Final = _bit("SENSOR_DATA", "LOAD_CELL_FORCE")
_SD_SPRUNG_ACCEL_BIT: Final = _bit("SENSOR_DATA", "SPRUNG_ACCEL")
_RS_SUPPLY_PRESSURE_BIT: Final = _bit("RIG_STATUS", "SUPPLY_PRESSURE")
_RS_SPOOL_POSITION_BIT: Final = _bit("RIG_STATUS", "SPOOL_POSITION")
_RS_LOAD_PRESSURE_BIT: Final = _bit("RIG_STATUS", "LOAD_PRESSURE")
_CS_STATE_BIT: Final = _bit("CONTROLLER_STATUS", "STATE")
_CS_ACTIVE_FAULT_BIT: Final = _bit("CONTROLLER_STATUS", "ACTIVE_FAULT")
_CS_OVERRUN_COUNT_BIT: Final = _bit("CONTROLLER_STATUS", "OVERRUN_COUNT")
_CS_BLENDING_BIT: Final = _bit("CONTROLLER_STATUS", "BLENDING")
_CS_WEIGHT_SET_BIT: Final = _bit("CONTROLLER_STATUS", "WEIGHT_SET")
_CS_JITTER_P99_BIT: Final = _bit("CONTROLLER_STATUS", "JITTER_P99")


class _Frame:
    """Base of the mutable, preallocated frame objects (``__slots__`` only)."""

    __slots__ = ("counter", "range_mask")
    FIELDS: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **values: Any) -> None:
        self.counter = 0
        self.range_mask = 0
        for name in self.FIELDS:
            setattr(self, name, 0)
        for name, value in values.items():
            if name not in self.FIELDS and name != "counter":
                raise TypeError(f"{type(self).__name__} has no field {name!r}")
            setattr(self, name, value)

    def __repr__(self) -> str:
        body = ", ".join(f"{n}={getattr(self, n)!r}" for n in ("counter", *self.FIELDS))
        return f"{type(self).__name__}({body})"

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        names = ("counter", *self.FIELDS)
        return all(getattr(self, n) == getattr(other, n) for n in names)

    __hash__ = None  # type: ignore[assignment]


class ValveCommand(_Frame):
    __slots__ = ("enable", "force_reference_n", "lifecycle", "sensor_counter_echo",
                 "spool_command")
    FIELDS = ("enable", "lifecycle", "spool_command", "force_reference_n",
              "sensor_counter_echo")
    enable: int
    lifecycle: int
    spool_command: float
    force_reference_n: float
    sensor_counter_echo: int


class FaultReport(_Frame):
    __slots__ = ("fault_code", "fault_detail", "fault_state", "fault_tick")
    FIELDS = ("fault_state", "fault_code", "fault_tick", "fault_detail")
    fault_state: int
    fault_code: int
    fault_tick: int
    fault_detail: int


class SensorData(_Frame):
    __slots__ = ("load_cell_force_n", "rattlespace_m", "sensor_status", "sprung_accel_mps2")
    FIELDS = ("sensor_status", "rattlespace_m", "load_cell_force_n", "sprung_accel_mps2")
    sensor_status: int
    rattlespace_m: float
    load_cell_force_n: float
    sprung_accel_mps2: float


class RigStatus(_Frame):
    __slots__ = ("bypass_open", "load_pressure_pa", "spool_position", "supply_ok",
                 "supply_pressure_pa", "watchdog_tripped")
    FIELDS = ("bypass_open", "watchdog_tripped", "supply_ok", "supply_pressure_pa",
              "spool_position", "load_pressure_pa")
    bypass_open: int
    watchdog_tripped: int
    supply_ok: int
    supply_pressure_pa: float
    spool_position: float
    load_pressure_pa: float


class ControllerStatus(_Frame):
    __slots__ = ("active_fault", "blending", "jitter_p99_s", "overrun_count", "state",
                 "weight_set")
    FIELDS = ("state", "active_fault", "overrun_count", "blending", "weight_set",
              "jitter_p99_s")
    state: int
    active_fault: int
    overrun_count: int
    blending: int
    weight_set: int
    jitter_p99_s: float


class _Codec:
    """Common part of the frame codecs."""

    FRAME_ID: ClassVar[int]
    NAME: ClassVar[str]
    FRAME_TYPE: ClassVar[type[_Frame]]
    COUNTER_SIGNAL: ClassVar[str]
    SIGNALS: ClassVar[tuple[SignalSpec, ...]]

    def __init__(self) -> None:
        self.frame_id = self.FRAME_ID
        self.name = self.NAME
        self._start = frame_crc_start(self.FRAME_ID)

    def _crc(self, data: bytes | bytearray | memoryview) -> int:
        w1, w2, w3, b7 = _WORDS.unpack_from(data)
        t2 = _T2
        s = t2[(self._start << 8) ^ w1]
        s = t2[(s << 8) ^ w2]
        s = t2[(s << 8) ^ w3]
        return _T1[s ^ b7] ^ 0xFF

    def new(self) -> Any:
        """A fresh (zeroed) frame object for :meth:`decode`."""
        return self.FRAME_TYPE()

    def encode_frame(self, buf: bytearray | memoryview, frame: _Frame) -> int:
        """Encode a frame object (its ``counter`` and fields); returns the clamp mask."""
        args = [getattr(frame, n) for n in self.FRAME_TYPE.FIELDS]
        return int(self.encode(buf, frame.counter, *args))  # type: ignore[attr-defined]

    def encode_signals(self, buf: bytearray | memoryview, signals: Mapping[str, float]) -> int:
        """Encode from a ``{DBC signal name: physical value}`` mapping (CRC signal ignored,
        missing signals 0).  Not for the hot path."""
        frame = self.FRAME_TYPE()
        frame.counter = int(signals.get(self.COUNTER_SIGNAL, 0))
        for spec in self.SIGNALS:
            setattr(frame, spec.attr, signals.get(spec.dbc_name, 0))
        return self.encode_frame(buf, frame)

    def to_signals(self, frame: _Frame) -> dict[str, float]:
        """``{DBC signal name: value}`` of a decoded frame (counter included, CRC not)."""
        out: dict[str, float] = {self.COUNTER_SIGNAL: frame.counter}
        for spec in self.SIGNALS:
            out[spec.dbc_name] = getattr(frame, spec.attr)
        return out


class ValveCommandCodec(_Codec):
    """ValveCommand, controller -> rig, every tick."""

    FRAME_ID = VALVE_COMMAND_ID
    NAME = VALVE_COMMAND_NAME
    FRAME_TYPE = ValveCommand
    COUNTER_SIGNAL = VALVE_COMMAND_COUNTER_SIGNAL
    SIGNALS = _specs("VALVE_COMMAND")
    _S = struct.Struct(VALVE_COMMAND_STRUCT)

    def encode(self, buf: bytearray | memoryview, counter: int, enable: int, lifecycle: int,
               spool_command: float, force_reference_n: float,
               sensor_counter_echo: int) -> int:
        m = 0
        if not VALVE_COMMAND_LIFECYCLE_MIN <= lifecycle <= VALVE_COMMAND_LIFECYCLE_MAX:
            m |= _VC_LIFECYCLE_BIT
            lifecycle = (VALVE_COMMAND_LIFECYCLE_MIN
                         if lifecycle < VALVE_COMMAND_LIFECYCLE_MIN
                         else VALVE_COMMAND_LIFECYCLE_MAX)
        elif lifecycle not in VALVE_COMMAND_LIFECYCLE_VALUES:
            m |= _VC_LIFECYCLE_BIT
        lo, hi = VALVE_COMMAND_SPOOL_COMMAND_MIN, VALVE_COMMAND_SPOOL_COMMAND_MAX
        if not lo <= spool_command <= hi:
            m |= _VC_SPOOL_COMMAND_BIT
            spool_command = lo if spool_command < lo else (hi if spool_command > hi else 0.0)
        lo, hi = VALVE_COMMAND_FORCE_REFERENCE_MIN, VALVE_COMMAND_FORCE_REFERENCE_MAX
        if not lo <= force_reference_n <= hi:
            m |= _VC_FORCE_REFERENCE_BIT
            force_reference_n = lo if force_reference_n < lo else (
                hi if force_reference_n > hi else 0.0)
        lo, hi = VALVE_COMMAND_SENSOR_COUNTER_ECHO_MIN, VALVE_COMMAND_SENSOR_COUNTER_ECHO_MAX
        if not lo <= sensor_counter_echo <= hi:
            m |= _VC_SENSOR_COUNTER_ECHO_BIT
            sensor_counter_echo = lo if sensor_counter_echo < lo else hi
        self._S.pack_into(
            buf, 0, 0,
            (counter & VALVE_COMMAND_COUNTER_MASK)
            | ((1 << VALVE_COMMAND_ENABLE_SHIFT) if enable else 0)
            | (lifecycle << VALVE_COMMAND_LIFECYCLE_SHIFT),
            round(spool_command / VALVE_COMMAND_SPOOL_COMMAND_SCALE),
            round(force_reference_n / VALVE_COMMAND_FORCE_REFERENCE_SCALE),
            sensor_counter_echo << VALVE_COMMAND_SENSOR_COUNTER_ECHO_SHIFT)
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: ValveCommand) -> DecodeStatus:
        if len(data) != VALVE_COMMAND_LENGTH:
            return _BAD_LENGTH
        crc, b1, spool, force, echo = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        lifecycle = (b1 >> VALVE_COMMAND_LIFECYCLE_SHIFT) & VALVE_COMMAND_LIFECYCLE_MASK
        m = 0 if lifecycle in VALVE_COMMAND_LIFECYCLE_VALUES else _VC_LIFECYCLE_BIT
        if not (VALVE_COMMAND_SPOOL_COMMAND_RAW_MIN <= spool
                <= VALVE_COMMAND_SPOOL_COMMAND_RAW_MAX):
            m |= _VC_SPOOL_COMMAND_BIT
        out.counter = b1 & VALVE_COMMAND_COUNTER_MASK
        out.enable = (b1 >> VALVE_COMMAND_ENABLE_SHIFT) & VALVE_COMMAND_ENABLE_MASK
        out.lifecycle = lifecycle
        out.spool_command = spool * VALVE_COMMAND_SPOOL_COMMAND_SCALE
        out.force_reference_n = force * VALVE_COMMAND_FORCE_REFERENCE_SCALE
        out.sensor_counter_echo = ((echo >> VALVE_COMMAND_SENSOR_COUNTER_ECHO_SHIFT)
                                   & VALVE_COMMAND_SENSOR_COUNTER_ECHO_MASK)
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class FaultReportCodec(_Codec):
    """FaultReport, controller -> rig, when a fault latches (and with the heartbeat).

    ``fault_tick`` is a tick counter and is taken modulo 2**32 like the rolling counter.
    """

    FRAME_ID = FAULT_REPORT_ID
    NAME = FAULT_REPORT_NAME
    FRAME_TYPE = FaultReport
    COUNTER_SIGNAL = FAULT_REPORT_COUNTER_SIGNAL
    SIGNALS = _specs("FAULT_REPORT")
    _S = struct.Struct(FAULT_REPORT_STRUCT)

    def encode(self, buf: bytearray | memoryview, counter: int, fault_state: int,
               fault_code: int, fault_tick: int, fault_detail: int) -> int:
        m = 0
        lo, hi = FAULT_REPORT_FAULT_STATE_MIN, FAULT_REPORT_FAULT_STATE_MAX
        if not lo <= fault_state <= hi:
            m |= _FR_FAULT_STATE_BIT
            fault_state = lo if fault_state < lo else hi
        elif fault_state not in FAULT_REPORT_FAULT_STATE_VALUES:
            m |= _FR_FAULT_STATE_BIT
        lo, hi = FAULT_REPORT_FAULT_CODE_MIN, FAULT_REPORT_FAULT_CODE_MAX
        if not lo <= fault_code <= hi:
            m |= _FR_FAULT_CODE_BIT
            fault_code = lo if fault_code < lo else hi
        elif fault_code not in FAULT_REPORT_FAULT_CODE_VALUES:
            m |= _FR_FAULT_CODE_BIT
        lo, hi = FAULT_REPORT_FAULT_DETAIL_MIN, FAULT_REPORT_FAULT_DETAIL_MAX
        if not lo <= fault_detail <= hi:
            m |= _FR_FAULT_DETAIL_BIT
            fault_detail = lo if fault_detail < lo else hi
        self._S.pack_into(buf, 0, 0,
                          (counter & FAULT_REPORT_COUNTER_MASK)
                          | (fault_state << FAULT_REPORT_FAULT_STATE_SHIFT),
                          fault_code, fault_tick % (FAULT_REPORT_FAULT_TICK_RAW_MAX + 1),
                          fault_detail)
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: FaultReport) -> DecodeStatus:
        if len(data) != FAULT_REPORT_LENGTH:
            return _BAD_LENGTH
        crc, b1, code, tick, detail = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        state = (b1 >> FAULT_REPORT_FAULT_STATE_SHIFT) & FAULT_REPORT_FAULT_STATE_MASK
        m = 0 if state in FAULT_REPORT_FAULT_STATE_VALUES else _FR_FAULT_STATE_BIT
        if code not in FAULT_REPORT_FAULT_CODE_VALUES:
            m |= _FR_FAULT_CODE_BIT
        out.counter = b1 & FAULT_REPORT_COUNTER_MASK
        out.fault_state = state
        out.fault_code = code
        out.fault_tick = tick
        out.fault_detail = detail
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class SensorDataCodec(_Codec):
    """SensorData, rig -> controller, every tick."""

    FRAME_ID = SENSOR_DATA_ID
    NAME = SENSOR_DATA_NAME
    FRAME_TYPE = SensorData
    COUNTER_SIGNAL = SENSOR_DATA_COUNTER_SIGNAL
    SIGNALS = _specs("SENSOR_DATA")
    _S = struct.Struct(SENSOR_DATA_STRUCT)

    def encode(self, buf: bytearray | memoryview, counter: int, sensor_status: int,
               rattlespace_m: float, load_cell_force_n: float,
               sprung_accel_mps2: float) -> int:
        m = 0
        s_lo, s_hi = SENSOR_DATA_SENSOR_STATUS_MIN, SENSOR_DATA_SENSOR_STATUS_MAX
        if not s_lo <= sensor_status <= s_hi:
            m |= _SD_SENSOR_STATUS_BIT
            sensor_status = s_lo if sensor_status < s_lo else s_hi
        lo, hi = SENSOR_DATA_RATTLESPACE_MIN, SENSOR_DATA_RATTLESPACE_MAX
        if not lo <= rattlespace_m <= hi:
            m |= _SD_RATTLESPACE_BIT
            rattlespace_m = lo if rattlespace_m < lo else (hi if rattlespace_m > hi else 0.0)
        lo, hi = SENSOR_DATA_LOAD_CELL_FORCE_MIN, SENSOR_DATA_LOAD_CELL_FORCE_MAX
        if not lo <= load_cell_force_n <= hi:
            m |= _SD_LOAD_CELL_FORCE_BIT
            load_cell_force_n = lo if load_cell_force_n < lo else (
                hi if load_cell_force_n > hi else 0.0)
        lo, hi = SENSOR_DATA_SPRUNG_ACCEL_MIN, SENSOR_DATA_SPRUNG_ACCEL_MAX
        if not lo <= sprung_accel_mps2 <= hi:
            m |= _SD_SPRUNG_ACCEL_BIT
            sprung_accel_mps2 = lo if sprung_accel_mps2 < lo else (
                hi if sprung_accel_mps2 > hi else 0.0)
        self._S.pack_into(buf, 0, 0,
                          (counter & SENSOR_DATA_COUNTER_MASK)
                          | (sensor_status << SENSOR_DATA_SENSOR_STATUS_SHIFT),
                          round(rattlespace_m / SENSOR_DATA_RATTLESPACE_SCALE),
                          round(load_cell_force_n / SENSOR_DATA_LOAD_CELL_FORCE_SCALE),
                          round(sprung_accel_mps2 / SENSOR_DATA_SPRUNG_ACCEL_SCALE))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: SensorData) -> DecodeStatus:
        if len(data) != SENSOR_DATA_LENGTH:
            return _BAD_LENGTH
        crc, b1, rs, force, acc = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        out.counter = b1 & SENSOR_DATA_COUNTER_MASK
        out.sensor_status = ((b1 >> SENSOR_DATA_SENSOR_STATUS_SHIFT)
                             & SENSOR_DATA_SENSOR_STATUS_MASK)
        out.rattlespace_m = rs * SENSOR_DATA_RATTLESPACE_SCALE
        out.load_cell_force_n = force * SENSOR_DATA_LOAD_CELL_FORCE_SCALE
        out.sprung_accel_mps2 = acc * SENSOR_DATA_SPRUNG_ACCEL_SCALE
        out.range_mask = 0  # every raw value of this frame is inside its DBC range
        return _OK


class RigStatusCodec(_Codec):
    """RigStatus, rig -> controller, 100 Hz."""

    FRAME_ID = RIG_STATUS_ID
    NAME = RIG_STATUS_NAME
    FRAME_TYPE = RigStatus
    COUNTER_SIGNAL = RIG_STATUS_COUNTER_SIGNAL
    SIGNALS = _specs("RIG_STATUS")
    _S = struct.Struct(RIG_STATUS_STRUCT)

    def encode(self, buf: bytearray | memoryview, counter: int, bypass_open: int,
               watchdog_tripped: int, supply_ok: int, supply_pressure_pa: float,
               spool_position: float, load_pressure_pa: float) -> int:
        m = 0
        lo, hi = RIG_STATUS_SUPPLY_PRESSURE_MIN, RIG_STATUS_SUPPLY_PRESSURE_MAX
        if not lo <= supply_pressure_pa <= hi:
            m |= _RS_SUPPLY_PRESSURE_BIT
            supply_pressure_pa = lo if supply_pressure_pa < lo else (
                hi if supply_pressure_pa > hi else 0.0)
        lo, hi = RIG_STATUS_SPOOL_POSITION_MIN, RIG_STATUS_SPOOL_POSITION_MAX
        if not lo <= spool_position <= hi:
            m |= _RS_SPOOL_POSITION_BIT
            spool_position = lo if spool_position < lo else (
                hi if spool_position > hi else 0.0)
        lo, hi = RIG_STATUS_LOAD_PRESSURE_MIN, RIG_STATUS_LOAD_PRESSURE_MAX
        if not lo <= load_pressure_pa <= hi:
            m |= _RS_LOAD_PRESSURE_BIT
            load_pressure_pa = lo if load_pressure_pa < lo else (
                hi if load_pressure_pa > hi else 0.0)
        b1 = ((counter & RIG_STATUS_COUNTER_MASK)
              | ((1 << RIG_STATUS_BYPASS_OPEN_SHIFT) if bypass_open else 0)
              | ((1 << RIG_STATUS_WATCHDOG_TRIPPED_SHIFT) if watchdog_tripped else 0)
              | ((1 << RIG_STATUS_SUPPLY_OK_SHIFT) if supply_ok else 0))
        self._S.pack_into(buf, 0, 0, b1,
                          round(supply_pressure_pa / RIG_STATUS_SUPPLY_PRESSURE_SCALE),
                          round(spool_position / RIG_STATUS_SPOOL_POSITION_SCALE),
                          round(load_pressure_pa / RIG_STATUS_LOAD_PRESSURE_SCALE))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: RigStatus) -> DecodeStatus:
        if len(data) != RIG_STATUS_LENGTH:
            return _BAD_LENGTH
        crc, b1, supply, spool, load = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        m = (0 if RIG_STATUS_SPOOL_POSITION_RAW_MIN <= spool
             <= RIG_STATUS_SPOOL_POSITION_RAW_MAX else _RS_SPOOL_POSITION_BIT)
        out.counter = b1 & RIG_STATUS_COUNTER_MASK
        out.bypass_open = (b1 >> RIG_STATUS_BYPASS_OPEN_SHIFT) & RIG_STATUS_BYPASS_OPEN_MASK
        out.watchdog_tripped = ((b1 >> RIG_STATUS_WATCHDOG_TRIPPED_SHIFT)
                                & RIG_STATUS_WATCHDOG_TRIPPED_MASK)
        out.supply_ok = (b1 >> RIG_STATUS_SUPPLY_OK_SHIFT) & RIG_STATUS_SUPPLY_OK_MASK
        out.supply_pressure_pa = supply * RIG_STATUS_SUPPLY_PRESSURE_SCALE
        out.spool_position = spool * RIG_STATUS_SPOOL_POSITION_SCALE
        out.load_pressure_pa = load * RIG_STATUS_LOAD_PRESSURE_SCALE
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class ControllerStatusCodec(_Codec):
    """ControllerStatus, controller -> rig, heartbeat."""

    FRAME_ID = CONTROLLER_STATUS_ID
    NAME = CONTROLLER_STATUS_NAME
    FRAME_TYPE = ControllerStatus
    COUNTER_SIGNAL = CONTROLLER_STATUS_COUNTER_SIGNAL
    SIGNALS = _specs("CONTROLLER_STATUS")
    _S = struct.Struct(CONTROLLER_STATUS_STRUCT)

    def encode(self, buf: bytearray | memoryview, counter: int, state: int, active_fault: int,
               overrun_count: int, blending: int, weight_set: int,
               jitter_p99_s: float) -> int:
        m = 0
        lo, hi = CONTROLLER_STATUS_STATE_MIN, CONTROLLER_STATUS_STATE_MAX
        if not lo <= state <= hi:
            m |= _CS_STATE_BIT
            state = lo if state < lo else hi
        elif state not in CONTROLLER_STATUS_STATE_VALUES:
            m |= _CS_STATE_BIT
        lo, hi = CONTROLLER_STATUS_ACTIVE_FAULT_MIN, CONTROLLER_STATUS_ACTIVE_FAULT_MAX
        if not lo <= active_fault <= hi:
            m |= _CS_ACTIVE_FAULT_BIT
            active_fault = lo if active_fault < lo else hi
        elif active_fault not in CONTROLLER_STATUS_ACTIVE_FAULT_VALUES:
            m |= _CS_ACTIVE_FAULT_BIT
        lo, hi = CONTROLLER_STATUS_OVERRUN_COUNT_MIN, CONTROLLER_STATUS_OVERRUN_COUNT_MAX
        if not lo <= overrun_count <= hi:
            m |= _CS_OVERRUN_COUNT_BIT
            overrun_count = lo if overrun_count < lo else hi
        lo, hi = CONTROLLER_STATUS_BLENDING_MIN, CONTROLLER_STATUS_BLENDING_MAX
        if not lo <= blending <= hi:
            m |= _CS_BLENDING_BIT
            blending = lo if blending < lo else hi
        elif blending not in CONTROLLER_STATUS_BLENDING_VALUES:
            m |= _CS_BLENDING_BIT
        lo, hi = CONTROLLER_STATUS_WEIGHT_SET_MIN, CONTROLLER_STATUS_WEIGHT_SET_MAX
        if not lo <= weight_set <= hi:
            m |= _CS_WEIGHT_SET_BIT
            weight_set = lo if weight_set < lo else hi
        lo_s, hi_s = CONTROLLER_STATUS_JITTER_P99_MIN, CONTROLLER_STATUS_JITTER_P99_MAX
        if not lo_s <= jitter_p99_s <= hi_s:
            m |= _CS_JITTER_P99_BIT
            jitter_p99_s = lo_s if jitter_p99_s < lo_s else (
                hi_s if jitter_p99_s > hi_s else 0.0)
        self._S.pack_into(buf, 0, 0,
                          (counter & CONTROLLER_STATUS_COUNTER_MASK)
                          | (state << CONTROLLER_STATUS_STATE_SHIFT),
                          active_fault, overrun_count,
                          (blending << CONTROLLER_STATUS_BLENDING_SHIFT)
                          | (weight_set << CONTROLLER_STATUS_WEIGHT_SET_SHIFT),
                          round(jitter_p99_s / CONTROLLER_STATUS_JITTER_P99_SCALE))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview,
               out: ControllerStatus) -> DecodeStatus:
        if len(data) != CONTROLLER_STATUS_LENGTH:
            return _BAD_LENGTH
        crc, b1, fault, overruns, b5, jitter = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        state = (b1 >> CONTROLLER_STATUS_STATE_SHIFT) & CONTROLLER_STATUS_STATE_MASK
        blending = ((b5 >> CONTROLLER_STATUS_BLENDING_SHIFT)
                    & CONTROLLER_STATUS_BLENDING_MASK)
        m = 0 if state in CONTROLLER_STATUS_STATE_VALUES else _CS_STATE_BIT
        if fault not in CONTROLLER_STATUS_ACTIVE_FAULT_VALUES:
            m |= _CS_ACTIVE_FAULT_BIT
        if blending not in CONTROLLER_STATUS_BLENDING_VALUES:
            m |= _CS_BLENDING_BIT
        out.counter = b1 & CONTROLLER_STATUS_COUNTER_MASK
        out.state = state
        out.active_fault = fault
        out.overrun_count = overruns
        out.blending = blending
        out.weight_set = ((b5 >> CONTROLLER_STATUS_WEIGHT_SET_SHIFT)
                          & CONTROLLER_STATUS_WEIGHT_SET_MASK)
        out.jitter_p99_s = jitter * CONTROLLER_STATUS_JITTER_P99_SCALE
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


VALVE_COMMAND: Final = ValveCommandCodec()
FAULT_REPORT: Final = FaultReportCodec()
SENSOR_DATA: Final = SensorDataCodec()
RIG_STATUS: Final = RigStatusCodec()
CONTROLLER_STATUS: Final = ControllerStatusCodec()
#: frame ID -> codec
CODECS: Final[Mapping[int, _Codec]] = {
    c.FRAME_ID: c for c in (VALVE_COMMAND, FAULT_REPORT, SENSOR_DATA, RIG_STATUS,
                            CONTROLLER_STATUS)
}


class FrameDecoder:
    """Decode any frame of the protocol by ID into preallocated per-ID objects.

    ``status = dec.decode(msg.arbitration_id, msg.data)``; on OK / OUT_OF_RANGE the
    values are in ``dec.frames[frame_id]`` (also ``dec.sensor_data`` etc.).  Unknown IDs
    (and extended IDs: pass ``is_extended=True``) give UNKNOWN_ID.  Never raises for a
    bytes-like payload of any length.
    """

    def __init__(self) -> None:
        self.valve_command = ValveCommand()
        self.fault_report = FaultReport()
        self.sensor_data = SensorData()
        self.rig_status = RigStatus()
        self.controller_status = ControllerStatus()
        self.frames: dict[int, _Frame] = {
            VALVE_COMMAND_ID: self.valve_command,
            FAULT_REPORT_ID: self.fault_report,
            SENSOR_DATA_ID: self.sensor_data,
            RIG_STATUS_ID: self.rig_status,
            CONTROLLER_STATUS_ID: self.controller_status,
        }
        self._dispatch: dict[int, tuple[Any, _Frame]] = {
            fid: (CODECS[fid], frame) for fid, frame in self.frames.items()
        }

    def decode(self, frame_id: int, data: bytes | bytearray | memoryview,
               is_extended: bool = False) -> DecodeStatus:
        entry = None if is_extended else self._dispatch.get(frame_id)
        if entry is None:
            return _UNKNOWN_ID
        codec, frame = entry
        status: DecodeStatus = codec.decode(data, frame)
        return status
