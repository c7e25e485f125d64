"""The rig's CAN protocol: frame IDs, enumerations and a fast codec for ``rig/wire/rig.dbc``.

The DBC is the source of truth and cantools the reference codec; this module is a
hand-compiled equivalent (``struct`` layouts, precomputed CRC tables) proven
byte-identical to cantools by ``tests/test_protocol.py``.  Hot-path use::

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

VALVE_COMMAND_ID: Final = 0x080
FAULT_REPORT_ID: Final = 0x081
SENSOR_DATA_ID: Final = 0x100
RIG_STATUS_ID: Final = 0x200
CONTROLLER_STATUS_ID: Final = 0x300
FRAME_LENGTH: Final = 8
#: frames each role receives (receive filters of :func:`rig.bus.core.open_bus`)
CONTROLLER_RX_IDS: Final = (SENSOR_DATA_ID, RIG_STATUS_ID)
RIG_RX_IDS: Final = (VALVE_COMMAND_ID, FAULT_REPORT_ID, CONTROLLER_STATUS_ID)


class FaultCode(IntEnum):
    """DBC ``VAL_ 129 FaultCode`` / ``VAL_ 768 ActiveFault``."""

    NONE = 0
    SENSOR_STALE = 1
    SENSOR_CRC = 2
    SENSOR_COUNTER = 3
    SENSOR_RANGE = 4
    NONFINITE = 5
    ESTIMATOR_DIVERGED = 6
    OVERRUN_STREAK = 7
    BUS_ERROR = 8
    BUS_OFF = 9
    EXCEPTION = 10
    RIG_WATCHDOG = 11
    SUPPLY_LOSS = 12
    SENSOR_STATUS = 13
    SHUTDOWN = 14
    SENSOR_FROZEN = 15
    #: not a latched fault: ControllerStatus.ActiveFault while ACTIVE and the bank runs its
    #: conservative law (StepFlag.DEGRADED); the lifecycle stays ACTIVE
    ESTIMATOR_DEGRADED = 16

    @property
    def description(self) -> str:
        """What the code means, in plain language for the rig engineer (event tables,
        reports); the condition and the detail byte per code: docs/service.md."""
        return _FAULT_DESCRIPTIONS[self]


_FAULT_DESCRIPTIONS: Final[dict[FaultCode, str]] = {
    FaultCode.NONE: "No fault.",
    FaultCode.SENSOR_STALE:
        "No valid SensorData frame for longer than safety.stale_ticks: the controller "
        "could no longer see the rig.",
    FaultCode.SENSOR_CRC:
        "A SensorData or RigStatus frame failed its end-to-end check (CRC or length): "
        "it was corrupted on the way.",
    FaultCode.SENSOR_COUNTER:
        "A frame's rolling counter repeated or jumped: the sender is stuck or frames "
        "were lost.",
    FaultCode.SENSOR_RANGE:
        "A sensor reading (rattlespace, force or acceleration) left its valid range.",
    FaultCode.NONFINITE:
        "A sensor value, the estimator state, the force reference or the spool command "
        "was not a finite number.",
    FaultCode.ESTIMATOR_DIVERGED:
        "The Kalman filter bank's estimate became unusable: every tire model's "
        "innovation stayed beyond a sensor's range for a whole monitor window.",
    FaultCode.OVERRUN_STREAK:
        "The control loop woke up late on too many consecutive ticks "
        "(safety.overrun_streak): its timing could not be trusted.",
    FaultCode.BUS_ERROR:
        "The CAN bus reported an error: a send or receive failed, or an error frame "
        "arrived.",
    FaultCode.BUS_OFF: "The CAN controller went bus-off or the interface disappeared.",
    FaultCode.EXCEPTION: "The control tick raised an unexpected exception.",
    FaultCode.RIG_WATCHDOG:
        "The rig's drive watchdog tripped: no valid valve command reached the drive "
        "within its timeout, so the drive opened the bypass on its own.",
    FaultCode.SUPPLY_LOSS: "The rig reported loss of hydraulic supply pressure.",
    FaultCode.SENSOR_STATUS:
        "A sensor reported its own fault (SensorStatus: LVDT, load cell or "
        "accelerometer).",
    FaultCode.SHUTDOWN:
        "The service was stopping: valve to its safe state (not a latched fault).",
    FaultCode.SENSOR_FROZEN:
        "A sensor value stayed bit-identical for more than safety.frozen_ticks frames "
        "while its counter advanced: the sensor is frozen.",
    FaultCode.ESTIMATOR_DEGRADED:
        "Not a latched fault: the estimator monitor found that no tire model fits the "
        "measurements (windowed innovation statistic above its chi-square level), so the "
        "bank commands zero force (the actuator follows the body, transparent) until the "
        "statistic recovers and it re-arms by itself.",
}


class Blending(IntEnum):
    """DBC ``VAL_ 768 Blending``: how the bank's model forces are combined.  The names
    users type for these modes live in :mod:`controller.modes`."""

    FUZZY = 0
    BAYES = 1
    MOVING = 2
    LQG = 3


class LifecycleState(IntEnum):
    """DBC ``VAL_ ... Lifecycle / FaultState / State``."""

    INACTIVE = 0
    ACTIVE = 1
    FAULT = 2
    STOPPING = 3


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


_LIFECYCLE_VALUES: Final = frozenset(int(v) for v in LifecycleState)
_FAULT_VALUES: Final = frozenset(int(v) for v in FaultCode)
_BLENDING_VALUES: Final = frozenset(int(v) for v in Blending)
_SPOOL_SCALE: Final = 3.05185094759972e-05  # 1/32767 as written in the DBC
_OK, _BAD_LENGTH, _UNKNOWN_ID, _BAD_CRC, _OUT_OF_RANGE = (
    DecodeStatus.OK, DecodeStatus.BAD_LENGTH, DecodeStatus.UNKNOWN_ID, DecodeStatus.BAD_CRC,
    DecodeStatus.OUT_OF_RANGE,
)
_WORDS: Final = struct.Struct(">xHHHB")
_T1: Final = CRC8_TABLE
_T2: Final = CRC8_TABLE2


def _raw_limit(x: float, scale: float) -> int:
    return round(x / scale)


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
    """0x080 ValveCommand, controller -> rig, every tick."""

    FRAME_ID = VALVE_COMMAND_ID
    NAME = "ValveCommand"
    FRAME_TYPE = ValveCommand
    COUNTER_SIGNAL = "ValveCommand_Counter"
    SIGNALS = (
        SignalSpec("enable", "Enable", 12, 1, False, 1, 0, 1),
        SignalSpec("lifecycle", "Lifecycle", 13, 3, False, 1, 0, 7,
                   tuple(sorted(_LIFECYCLE_VALUES))),
        SignalSpec("spool_command", "SpoolCommand", 16, 16, True, _SPOOL_SCALE, -1.0, 1.0),
        SignalSpec("force_reference_n", "ForceReference", 32, 16, True, 0.5, -16384.0,
                   16383.5),
        SignalSpec("sensor_counter_echo", "SensorCounterEcho", 48, 4, False, 1, 0, 15),
    )
    _S = struct.Struct("<BBhhBx")
    _SPOOL_RAW_LO = _raw_limit(-1.0, _SPOOL_SCALE)
    _SPOOL_RAW_HI = _raw_limit(1.0, _SPOOL_SCALE)

    def encode(self, buf: bytearray | memoryview, counter: int, enable: int, lifecycle: int,
               spool_command: float, force_reference_n: float,
               sensor_counter_echo: int) -> int:
        m = 0
        if not 0 <= lifecycle <= 7:
            m |= 2
            lifecycle = 0 if lifecycle < 0 else 7
        elif lifecycle not in _LIFECYCLE_VALUES:
            m |= 2
        if not -1.0 <= spool_command <= 1.0:
            m |= 4
            spool_command = -1.0 if spool_command < -1.0 else (
                1.0 if spool_command > 1.0 else 0.0)
        if not -16384.0 <= force_reference_n <= 16383.5:
            m |= 8
            force_reference_n = -16384.0 if force_reference_n < -16384.0 else (
                16383.5 if force_reference_n > 16383.5 else 0.0)
        if not 0 <= sensor_counter_echo <= 15:
            m |= 16
            sensor_counter_echo = 0 if sensor_counter_echo < 0 else 15
        self._S.pack_into(buf, 0, 0,
                          (counter & 0xF) | (0x10 if enable else 0) | (lifecycle << 5),
                          round(spool_command / _SPOOL_SCALE), round(force_reference_n / 0.5),
                          sensor_counter_echo)
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: ValveCommand) -> DecodeStatus:
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, spool, force, echo = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        lifecycle = b1 >> 5
        m = 0 if lifecycle in _LIFECYCLE_VALUES else 2
        if not self._SPOOL_RAW_LO <= spool <= self._SPOOL_RAW_HI:
            m |= 4
        out.counter = b1 & 0xF
        out.enable = (b1 >> 4) & 1
        out.lifecycle = lifecycle
        out.spool_command = spool * _SPOOL_SCALE
        out.force_reference_n = force * 0.5
        out.sensor_counter_echo = echo & 0xF
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class FaultReportCodec(_Codec):
    """0x081 FaultReport, controller -> rig, when a fault latches (and with the heartbeat).

    ``fault_tick`` is a tick counter and is taken modulo 2**32 like the rolling counter.
    """

    FRAME_ID = FAULT_REPORT_ID
    NAME = "FaultReport"
    FRAME_TYPE = FaultReport
    COUNTER_SIGNAL = "FaultReport_Counter"
    SIGNALS = (
        SignalSpec("fault_state", "FaultState", 12, 4, False, 1, 0, 15,
                   tuple(sorted(_LIFECYCLE_VALUES))),
        SignalSpec("fault_code", "FaultCode", 16, 8, False, 1, 0, 255,
                   tuple(sorted(_FAULT_VALUES))),
        SignalSpec("fault_tick", "FaultTick", 24, 32, False, 1, 0, 4294967295),
        SignalSpec("fault_detail", "FaultDetail", 56, 8, False, 1, 0, 255),
    )
    _S = struct.Struct("<BBBIB")

    def encode(self, buf: bytearray | memoryview, counter: int, fault_state: int,
               fault_code: int, fault_tick: int, fault_detail: int) -> int:
        m = 0
        if not 0 <= fault_state <= 15:
            m |= 1
            fault_state = 0 if fault_state < 0 else 15
        elif fault_state not in _LIFECYCLE_VALUES:
            m |= 1
        if not 0 <= fault_code <= 255:
            m |= 2
            fault_code = 0 if fault_code < 0 else 255
        elif fault_code not in _FAULT_VALUES:
            m |= 2
        if not 0 <= fault_detail <= 255:
            m |= 8
            fault_detail = 0 if fault_detail < 0 else 255
        self._S.pack_into(buf, 0, 0, (counter & 0xF) | (fault_state << 4), fault_code,
                          fault_tick & 0xFFFFFFFF, fault_detail)
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: FaultReport) -> DecodeStatus:
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, code, tick, detail = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        state = b1 >> 4
        m = 0 if state in _LIFECYCLE_VALUES else 1
        if code not in _FAULT_VALUES:
            m |= 2
        out.counter = b1 & 0xF
        out.fault_state = state
        out.fault_code = code
        out.fault_tick = tick
        out.fault_detail = detail
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class SensorDataCodec(_Codec):
    """0x100 SensorData, rig -> controller, every tick."""

    FRAME_ID = SENSOR_DATA_ID
    NAME = "SensorData"
    FRAME_TYPE = SensorData
    COUNTER_SIGNAL = "SensorData_Counter"
    SIGNALS = (
        SignalSpec("sensor_status", "SensorStatus", 12, 4, False, 1, 0, 15),
        SignalSpec("rattlespace_m", "Rattlespace", 16, 16, True, 5e-06, -0.16384, 0.163835),
        SignalSpec("load_cell_force_n", "LoadCellForce", 32, 16, True, 0.5, -16384.0,
                   16383.5),
        SignalSpec("sprung_accel_mps2", "SprungAccel", 48, 16, True, 0.005, -163.84,
                   163.835),
    )
    _S = struct.Struct("<BBhhh")

    def encode(self, buf: bytearray | memoryview, counter: int, sensor_status: int,
               rattlespace_m: float, load_cell_force_n: float,
               sprung_accel_mps2: float) -> int:
        m = 0
        if not 0 <= sensor_status <= 15:
            m |= 1
            sensor_status = 0 if sensor_status < 0 else 15
        if not -0.16384 <= rattlespace_m <= 0.163835:
            m |= 2
            rattlespace_m = -0.16384 if rattlespace_m < -0.16384 else (
                0.163835 if rattlespace_m > 0.163835 else 0.0)
        if not -16384.0 <= load_cell_force_n <= 16383.5:
            m |= 4
            load_cell_force_n = -16384.0 if load_cell_force_n < -16384.0 else (
                16383.5 if load_cell_force_n > 16383.5 else 0.0)
        if not -163.84 <= sprung_accel_mps2 <= 163.835:
            m |= 8
            sprung_accel_mps2 = -163.84 if sprung_accel_mps2 < -163.84 else (
                163.835 if sprung_accel_mps2 > 163.835 else 0.0)
        self._S.pack_into(buf, 0, 0, (counter & 0xF) | (sensor_status << 4),
                          round(rattlespace_m / 5e-06), round(load_cell_force_n / 0.5),
                          round(sprung_accel_mps2 / 0.005))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: SensorData) -> DecodeStatus:
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, rs, force, acc = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        out.counter = b1 & 0xF
        out.sensor_status = b1 >> 4
        out.rattlespace_m = rs * 5e-06
        out.load_cell_force_n = force * 0.5
        out.sprung_accel_mps2 = acc * 0.005
        out.range_mask = 0  # every raw value of this frame is inside its DBC range
        return _OK


class RigStatusCodec(_Codec):
    """0x200 RigStatus, rig -> controller, 100 Hz."""

    FRAME_ID = RIG_STATUS_ID
    NAME = "RigStatus"
    FRAME_TYPE = RigStatus
    COUNTER_SIGNAL = "RigStatus_Counter"
    SIGNALS = (
        SignalSpec("bypass_open", "BypassOpen", 12, 1, False, 1, 0, 1),
        SignalSpec("watchdog_tripped", "WatchdogTripped", 13, 1, False, 1, 0, 1),
        SignalSpec("supply_ok", "SupplyOk", 14, 1, False, 1, 0, 1),
        SignalSpec("supply_pressure_pa", "SupplyPressure", 16, 16, False, 1000, 0.0,
                   65535000.0),
        SignalSpec("spool_position", "SpoolPosition", 32, 16, True, _SPOOL_SCALE, -1.0, 1.0),
        SignalSpec("load_pressure_pa", "LoadPressure", 48, 16, True, 1000, -32768000.0,
                   32767000.0),
    )
    _S = struct.Struct("<BBHhh")
    _SPOOL_RAW_LO = _raw_limit(-1.0, _SPOOL_SCALE)
    _SPOOL_RAW_HI = _raw_limit(1.0, _SPOOL_SCALE)

    def encode(self, buf: bytearray | memoryview, counter: int, bypass_open: int,
               watchdog_tripped: int, supply_ok: int, supply_pressure_pa: float,
               spool_position: float, load_pressure_pa: float) -> int:
        m = 0
        if not 0.0 <= supply_pressure_pa <= 65535000.0:
            m |= 8
            supply_pressure_pa = 65535000.0 if supply_pressure_pa > 65535000.0 else 0.0
        if not -1.0 <= spool_position <= 1.0:
            m |= 16
            spool_position = -1.0 if spool_position < -1.0 else (
                1.0 if spool_position > 1.0 else 0.0)
        if not -32768000.0 <= load_pressure_pa <= 32767000.0:
            m |= 32
            load_pressure_pa = -32768000.0 if load_pressure_pa < -32768000.0 else (
                32767000.0 if load_pressure_pa > 32767000.0 else 0.0)
        b1 = ((counter & 0xF) | (0x10 if bypass_open else 0)
              | (0x20 if watchdog_tripped else 0) | (0x40 if supply_ok else 0))
        self._S.pack_into(buf, 0, 0, b1, round(supply_pressure_pa / 1000),
                          round(spool_position / _SPOOL_SCALE), round(load_pressure_pa / 1000))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: RigStatus) -> DecodeStatus:
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, supply, spool, load = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        m = 0 if self._SPOOL_RAW_LO <= spool <= self._SPOOL_RAW_HI else 16
        out.counter = b1 & 0xF
        out.bypass_open = (b1 >> 4) & 1
        out.watchdog_tripped = (b1 >> 5) & 1
        out.supply_ok = (b1 >> 6) & 1
        out.supply_pressure_pa = supply * 1000.0
        out.spool_position = spool * _SPOOL_SCALE
        out.load_pressure_pa = load * 1000.0
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class ControllerStatusCodec(_Codec):
    """0x300 ControllerStatus, controller -> rig, heartbeat."""

    FRAME_ID = CONTROLLER_STATUS_ID
    NAME = "ControllerStatus"
    FRAME_TYPE = ControllerStatus
    COUNTER_SIGNAL = "ControllerStatus_Counter"
    SIGNALS = (
        SignalSpec("state", "State", 12, 4, False, 1, 0, 15, tuple(sorted(_LIFECYCLE_VALUES))),
        SignalSpec("active_fault", "ActiveFault", 16, 8, False, 1, 0, 255,
                   tuple(sorted(_FAULT_VALUES))),
        SignalSpec("overrun_count", "OverrunCount", 24, 16, False, 1, 0, 65535),
        SignalSpec("blending", "Blending", 40, 4, False, 1, 0, 15,
                   tuple(sorted(_BLENDING_VALUES))),
        SignalSpec("weight_set", "WeightSet", 44, 4, False, 1, 0, 15),
        SignalSpec("jitter_p99_s", "JitterP99", 48, 16, False, 1e-06, 0.0, 0.065535),
    )
    _S = struct.Struct("<BBBHBH")

    def encode(self, buf: bytearray | memoryview, counter: int, state: int, active_fault: int,
               overrun_count: int, blending: int, weight_set: int,
               jitter_p99_s: float) -> int:
        m = 0
        if not 0 <= state <= 15:
            m |= 1
            state = 0 if state < 0 else 15
        elif state not in _LIFECYCLE_VALUES:
            m |= 1
        if not 0 <= active_fault <= 255:
            m |= 2
            active_fault = 0 if active_fault < 0 else 255
        elif active_fault not in _FAULT_VALUES:
            m |= 2
        if not 0 <= overrun_count <= 65535:
            m |= 4
            overrun_count = 0 if overrun_count < 0 else 65535
        if not 0 <= blending <= 15:
            m |= 8
            blending = 0 if blending < 0 else 15
        elif blending not in _BLENDING_VALUES:
            m |= 8
        if not 0 <= weight_set <= 15:
            m |= 16
            weight_set = 0 if weight_set < 0 else 15
        if not 0.0 <= jitter_p99_s <= 0.065535:
            m |= 32
            jitter_p99_s = 0.065535 if jitter_p99_s > 0.065535 else 0.0
        self._S.pack_into(buf, 0, 0, (counter & 0xF) | (state << 4), active_fault,
                          overrun_count, blending | (weight_set << 4),
                          round(jitter_p99_s / 1e-06))
        buf[0] = self._crc(buf)
        return m

    def decode(self, data: bytes | bytearray | memoryview,
               out: ControllerStatus) -> DecodeStatus:
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, fault, overruns, b5, jitter = self._S.unpack(data)
        if crc != self._crc(data):
            return _BAD_CRC
        state = b1 >> 4
        blending = b5 & 0xF
        m = 0 if state in _LIFECYCLE_VALUES else 1
        if fault not in _FAULT_VALUES:
            m |= 2
        if blending not in _BLENDING_VALUES:
            m |= 8
        out.counter = b1 & 0xF
        out.state = state
        out.active_fault = fault
        out.overrun_count = overruns
        out.blending = blending
        out.weight_set = b5 >> 4
        out.jitter_p99_s = jitter * 1e-06
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
