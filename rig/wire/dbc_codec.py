"""Generated from rig.dbc by ``python -m rig.wire.generate``: do not edit.

The CAN codec: per frame of the DBC its frame class and its codec, ``encode`` and
``decode`` written out with the DBC's bit positions, scales, ranges and ``VAL_``
values as literals (behaviour: :mod:`rig.wire.protocol`; shared parts:
:mod:`rig.wire.codec_base`; E2E CRC tables: :mod:`rig.wire.e2e`).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Final

from rig.wire.codec_base import Codec, DecodeStatus, Frame, SignalSpec
from rig.wire.e2e import CRC8_TABLE, CRC8_TABLE2

_OK: Final = DecodeStatus.OK
_BAD_LENGTH: Final = DecodeStatus.BAD_LENGTH
_BAD_CRC: Final = DecodeStatus.BAD_CRC
_OUT_OF_RANGE: Final = DecodeStatus.OUT_OF_RANGE
_T1: Final = CRC8_TABLE
_T2: Final = CRC8_TABLE2
#: bytes 1-2, 3-4 and 5-6 as big-endian words and byte 7: the CRC's table lookups
_CRC_WORDS: Final = struct.Struct(">xHHHB").unpack_from
_VALVE_COMMAND_PACK: Final = struct.Struct('<BBhhBx').pack_into
_VALVE_COMMAND_UNPACK: Final = struct.Struct('<BBhhBx').unpack
_FAULT_REPORT_PACK: Final = struct.Struct('<BBBIB').pack_into
_FAULT_REPORT_UNPACK: Final = struct.Struct('<BBBIB').unpack
_SENSOR_DATA_PACK: Final = struct.Struct('<BBhhh').pack_into
_SENSOR_DATA_UNPACK: Final = struct.Struct('<BBhhh').unpack
_ROAD_PREVIEW_PACK: Final = struct.Struct('<BBhHBx').pack_into
_ROAD_PREVIEW_UNPACK: Final = struct.Struct('<BBhHBx').unpack
_RIG_STATUS_PACK: Final = struct.Struct('<BBHhh').pack_into
_RIG_STATUS_UNPACK: Final = struct.Struct('<BBHhh').unpack
_CONTROLLER_STATUS_PACK: Final = struct.Struct('<BBBHBH').pack_into
_CONTROLLER_STATUS_UNPACK: Final = struct.Struct('<BBBHBH').unpack


class ValveCommand(Frame):
    """ValveCommand as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('enable', 'force_reference_n', 'lifecycle', 'sensor_counter_echo', 'spool_command')
    FIELDS = ('enable', 'lifecycle', 'spool_command', 'force_reference_n', 'sensor_counter_echo')
    #: Enable : 12|1@1+ (1,0) [0|1] ""
    enable: int
    #: Lifecycle : 13|3@1+ (1,0) [0|7] ""
    lifecycle: int
    #: SpoolCommand : 16|16@1- (3.05185094759972e-05,0) [-1|1] ""
    spool_command: float
    #: ForceReference : 32|16@1- (0.5,0) [-16384|16383.5] "N"
    force_reference_n: float
    #: SensorCounterEcho : 48|4@1+ (1,0) [0|15] ""
    sensor_counter_echo: int


class ValveCommandCodec(Codec):
    """ValveCommand 0x080, Controller -> Rig, Cyclic every 1 ms."""

    FRAME_ID = 0x080
    NAME = 'ValveCommand'
    FRAME_TYPE = ValveCommand
    COUNTER_SIGNAL = 'ValveCommand_Counter'
    SIGNALS = (
        SignalSpec('enable', 'Enable', 12, 1, False, 1, 0, 1),
        SignalSpec('lifecycle', 'Lifecycle', 13, 3, False, 1, 0, 7, (0, 1, 2, 3)),
        SignalSpec('spool_command', 'SpoolCommand', 16, 16, True, 3.05185094759972e-05, -1.0, 1.0),
        SignalSpec('force_reference_n', 'ForceReference', 32, 16, True, 0.5, -16384.0, 16383.5),
        SignalSpec('sensor_counter_echo', 'SensorCounterEcho', 48, 4, False, 1, 0, 15),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, enable: int, lifecycle: int,
               spool_command: float, force_reference_n: float, sensor_counter_echo: int) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0 <= lifecycle <= 7:
            m |= 0x2  # Lifecycle
            lifecycle = 0 if lifecycle < 0 else 7
        elif lifecycle not in {0, 1, 2, 3}:
            m |= 0x2  # Lifecycle: no VAL_ value
        if not -1.0 <= spool_command <= 1.0:
            m |= 0x4  # SpoolCommand
            if spool_command < -1.0:
                spool_command = -1.0
            elif spool_command > 1.0:
                spool_command = 1.0
            else:  # NaN
                spool_command = 0.0
        if not -16384.0 <= force_reference_n <= 16383.5:
            m |= 0x8  # ForceReference
            if force_reference_n < -16384.0:
                force_reference_n = -16384.0
            elif force_reference_n > 16383.5:
                force_reference_n = 16383.5
            else:  # NaN
                force_reference_n = 0.0
        if not 0 <= sensor_counter_echo <= 15:
            m |= 0x10  # SensorCounterEcho
            sensor_counter_echo = 0 if sensor_counter_echo < 0 else 15
        b1 = ((counter & 0xf) | (0x10 if enable else 0) | (lifecycle << 5))
        _VALVE_COMMAND_PACK(buf, 0, 0, b1, round(spool_command / 3.05185094759972e-05),
                            round(force_reference_n / 0.5), sensor_counter_echo)
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0x8800 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: ValveCommand) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_spool_command, r_force_reference, b6 = _VALVE_COMMAND_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0x8800 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        m = 0
        lifecycle = b1 >> 5
        if lifecycle not in {0, 1, 2, 3}:
            m |= 0x2  # Lifecycle
        if not -32767 <= r_spool_command <= 32767:
            m |= 0x4  # SpoolCommand
        out.counter = b1 & 0xf
        out.enable = (b1 >> 4) & 0x1
        out.lifecycle = lifecycle
        out.spool_command = r_spool_command * 3.05185094759972e-05
        out.force_reference_n = r_force_reference * 0.5
        out.sensor_counter_echo = b6 & 0xf
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class FaultReport(Frame):
    """FaultReport as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('fault_code', 'fault_detail', 'fault_state', 'fault_tick')
    FIELDS = ('fault_state', 'fault_code', 'fault_tick', 'fault_detail')
    #: FaultState : 12|4@1+ (1,0) [0|15] ""
    fault_state: int
    #: FaultCode : 16|8@1+ (1,0) [0|255] ""
    fault_code: int
    #: FaultTick : 24|32@1+ (1,0) [0|4294967295] ""
    fault_tick: int
    #: FaultDetail : 56|8@1+ (1,0) [0|255] ""
    fault_detail: int


class FaultReportCodec(Codec):
    """FaultReport 0x081, Controller -> Rig, CyclicIfActive every 100 ms."""

    FRAME_ID = 0x081
    NAME = 'FaultReport'
    FRAME_TYPE = FaultReport
    COUNTER_SIGNAL = 'FaultReport_Counter'
    SIGNALS = (
        SignalSpec('fault_state', 'FaultState', 12, 4, False, 1, 0, 15, (0, 1, 2, 3)),
        SignalSpec('fault_code', 'FaultCode', 16, 8, False, 1, 0, 255,
                   (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16)),
        SignalSpec('fault_tick', 'FaultTick', 24, 32, False, 1, 0, 4294967295),
        SignalSpec('fault_detail', 'FaultDetail', 56, 8, False, 1, 0, 255),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, fault_state: int, fault_code: int,
               fault_tick: int, fault_detail: int) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0 <= fault_state <= 15:
            m |= 0x1  # FaultState
            fault_state = 0 if fault_state < 0 else 15
        elif fault_state not in {0, 1, 2, 3}:
            m |= 0x1  # FaultState: no VAL_ value
        if not 0 <= fault_code <= 255:
            m |= 0x2  # FaultCode
            fault_code = 0 if fault_code < 0 else 255
        elif fault_code not in {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16}:
            m |= 0x2  # FaultCode: no VAL_ value
        if not 0 <= fault_detail <= 255:
            m |= 0x8  # FaultDetail
            fault_detail = 0 if fault_detail < 0 else 255
        b1 = ((counter & 0xf) | (fault_state << 4))
        _FAULT_REPORT_PACK(buf, 0, 0, b1, fault_code, fault_tick % 4294967296, fault_detail)
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0xc400 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: FaultReport) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_fault_code, r_fault_tick, r_fault_detail = _FAULT_REPORT_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0xc400 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        m = 0
        fault_state = b1 >> 4
        if fault_state not in {0, 1, 2, 3}:
            m |= 0x1  # FaultState
        if r_fault_code not in {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16}:
            m |= 0x2  # FaultCode
        out.counter = b1 & 0xf
        out.fault_state = fault_state
        out.fault_code = r_fault_code
        out.fault_tick = r_fault_tick
        out.fault_detail = r_fault_detail
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class SensorData(Frame):
    """SensorData as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('load_cell_force_n', 'rattlespace_m', 'sensor_status', 'sprung_accel_mps2')
    FIELDS = ('sensor_status', 'rattlespace_m', 'load_cell_force_n', 'sprung_accel_mps2')
    #: SensorStatus : 12|4@1+ (1,0) [0|15] ""
    sensor_status: int
    #: Rattlespace : 16|16@1- (5e-06,0) [-0.16384|0.163835] "m"
    rattlespace_m: float
    #: LoadCellForce : 32|16@1- (0.5,0) [-16384|16383.5] "N"
    load_cell_force_n: float
    #: SprungAccel : 48|16@1- (0.005,0) [-163.84|163.835] "m/s^2"
    sprung_accel_mps2: float


class SensorDataCodec(Codec):
    """SensorData 0x100, Rig -> Controller, Cyclic every 1 ms."""

    FRAME_ID = 0x100
    NAME = 'SensorData'
    FRAME_TYPE = SensorData
    COUNTER_SIGNAL = 'SensorData_Counter'
    SIGNALS = (
        SignalSpec('sensor_status', 'SensorStatus', 12, 4, False, 1, 0, 15),
        SignalSpec('rattlespace_m', 'Rattlespace', 16, 16, True, 5e-06, -0.16384, 0.163835),
        SignalSpec('load_cell_force_n', 'LoadCellForce', 32, 16, True, 0.5, -16384.0, 16383.5),
        SignalSpec('sprung_accel_mps2', 'SprungAccel', 48, 16, True, 0.005, -163.84, 163.835),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, sensor_status: int,
               rattlespace_m: float, load_cell_force_n: float, sprung_accel_mps2: float) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0 <= sensor_status <= 15:
            m |= 0x1  # SensorStatus
            sensor_status = 0 if sensor_status < 0 else 15
        if not -0.16384 <= rattlespace_m <= 0.163835:
            m |= 0x2  # Rattlespace
            if rattlespace_m < -0.16384:
                rattlespace_m = -0.16384
            elif rattlespace_m > 0.163835:
                rattlespace_m = 0.163835
            else:  # NaN
                rattlespace_m = 0.0
        if not -16384.0 <= load_cell_force_n <= 16383.5:
            m |= 0x4  # LoadCellForce
            if load_cell_force_n < -16384.0:
                load_cell_force_n = -16384.0
            elif load_cell_force_n > 16383.5:
                load_cell_force_n = 16383.5
            else:  # NaN
                load_cell_force_n = 0.0
        if not -163.84 <= sprung_accel_mps2 <= 163.835:
            m |= 0x8  # SprungAccel
            if sprung_accel_mps2 < -163.84:
                sprung_accel_mps2 = -163.84
            elif sprung_accel_mps2 > 163.835:
                sprung_accel_mps2 = 163.835
            else:  # NaN
                sprung_accel_mps2 = 0.0
        b1 = ((counter & 0xf) | (sensor_status << 4))
        _SENSOR_DATA_PACK(buf, 0, 0, b1, round(rattlespace_m / 5e-06),
                          round(load_cell_force_n / 0.5), round(sprung_accel_mps2 / 0.005))
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0x5c00 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: SensorData) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_rattlespace, r_load_cell_force, r_sprung_accel = _SENSOR_DATA_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0x5c00 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        out.counter = b1 & 0xf
        out.sensor_status = b1 >> 4
        out.rattlespace_m = r_rattlespace * 5e-06
        out.load_cell_force_n = r_load_cell_force * 0.5
        out.sprung_accel_mps2 = r_sprung_accel * 0.005
        out.range_mask = 0  # every raw value of this frame is in range
        return _OK


class RoadPreview(Frame):
    """RoadPreview as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('preview_lead', 'preview_sensor_counter', 'preview_status', 'road_velocity_mps')
    FIELDS = ('preview_status', 'road_velocity_mps', 'preview_lead', 'preview_sensor_counter')
    #: PreviewStatus : 12|4@1+ (1,0) [0|15] ""
    preview_status: int
    #: RoadVelocity : 16|16@1- (0.001,0) [-32.768|32.767] "m/s"
    road_velocity_mps: float
    #: PreviewLead : 32|16@1+ (1,0) [0|65535] ""
    preview_lead: int
    #: PreviewSensorCounter : 48|4@1+ (1,0) [0|15] ""
    preview_sensor_counter: int


class RoadPreviewCodec(Codec):
    """RoadPreview 0x101, Rig -> Controller, Cyclic every 1 ms."""

    FRAME_ID = 0x101
    NAME = 'RoadPreview'
    FRAME_TYPE = RoadPreview
    COUNTER_SIGNAL = 'RoadPreview_Counter'
    SIGNALS = (
        SignalSpec('preview_status', 'PreviewStatus', 12, 4, False, 1, 0, 15),
        SignalSpec('road_velocity_mps', 'RoadVelocity', 16, 16, True, 0.001, -32.768, 32.767),
        SignalSpec('preview_lead', 'PreviewLead', 32, 16, False, 1, 0, 65535),
        SignalSpec('preview_sensor_counter', 'PreviewSensorCounter', 48, 4, False, 1, 0, 15),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, preview_status: int,
               road_velocity_mps: float, preview_lead: int, preview_sensor_counter: int) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0 <= preview_status <= 15:
            m |= 0x1  # PreviewStatus
            preview_status = 0 if preview_status < 0 else 15
        if not -32.768 <= road_velocity_mps <= 32.767:
            m |= 0x2  # RoadVelocity
            if road_velocity_mps < -32.768:
                road_velocity_mps = -32.768
            elif road_velocity_mps > 32.767:
                road_velocity_mps = 32.767
            else:  # NaN
                road_velocity_mps = 0.0
        if not 0 <= preview_lead <= 65535:
            m |= 0x4  # PreviewLead
            preview_lead = 0 if preview_lead < 0 else 65535
        if not 0 <= preview_sensor_counter <= 15:
            m |= 0x8  # PreviewSensorCounter
            preview_sensor_counter = 0 if preview_sensor_counter < 0 else 15
        b1 = ((counter & 0xf) | (preview_status << 4))
        _ROAD_PREVIEW_PACK(buf, 0, 0, b1, round(road_velocity_mps / 0.001), preview_lead,
                           preview_sensor_counter)
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0x1000 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: RoadPreview) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_road_velocity, r_preview_lead, b6 = _ROAD_PREVIEW_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0x1000 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        out.counter = b1 & 0xf
        out.preview_status = b1 >> 4
        out.road_velocity_mps = r_road_velocity * 0.001
        out.preview_lead = r_preview_lead
        out.preview_sensor_counter = b6 & 0xf
        out.range_mask = 0  # every raw value of this frame is in range
        return _OK


class RigStatus(Frame):
    """RigStatus as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('bypass_open', 'load_pressure_pa', 'spool_position', 'supply_ok',
                 'supply_pressure_pa', 'watchdog_tripped')
    FIELDS = ('bypass_open', 'watchdog_tripped', 'supply_ok', 'supply_pressure_pa',
              'spool_position', 'load_pressure_pa')
    #: BypassOpen : 12|1@1+ (1,0) [0|1] ""
    bypass_open: int
    #: WatchdogTripped : 13|1@1+ (1,0) [0|1] ""
    watchdog_tripped: int
    #: SupplyOk : 14|1@1+ (1,0) [0|1] ""
    supply_ok: int
    #: SupplyPressure : 16|16@1+ (1000,0) [0|65535000] "Pa"
    supply_pressure_pa: float
    #: SpoolPosition : 32|16@1- (3.05185094759972e-05,0) [-1|1] ""
    spool_position: float
    #: LoadPressure : 48|16@1- (1000,0) [-32768000|32767000] "Pa"
    load_pressure_pa: float


class RigStatusCodec(Codec):
    """RigStatus 0x200, Rig -> Controller, Cyclic every 10 ms."""

    FRAME_ID = 0x200
    NAME = 'RigStatus'
    FRAME_TYPE = RigStatus
    COUNTER_SIGNAL = 'RigStatus_Counter'
    SIGNALS = (
        SignalSpec('bypass_open', 'BypassOpen', 12, 1, False, 1, 0, 1),
        SignalSpec('watchdog_tripped', 'WatchdogTripped', 13, 1, False, 1, 0, 1),
        SignalSpec('supply_ok', 'SupplyOk', 14, 1, False, 1, 0, 1),
        SignalSpec('supply_pressure_pa', 'SupplyPressure', 16, 16, False, 1000.0, 0.0, 65535000.0),
        SignalSpec('spool_position', 'SpoolPosition', 32, 16, True, 3.05185094759972e-05, -1.0,
                   1.0),
        SignalSpec('load_pressure_pa', 'LoadPressure', 48, 16, True, 1000.0, -32768000.0,
                   32767000.0),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, bypass_open: int,
               watchdog_tripped: int, supply_ok: int, supply_pressure_pa: float,
               spool_position: float, load_pressure_pa: float) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0.0 <= supply_pressure_pa <= 65535000.0:
            m |= 0x8  # SupplyPressure
            if supply_pressure_pa < 0.0:
                supply_pressure_pa = 0.0
            elif supply_pressure_pa > 65535000.0:
                supply_pressure_pa = 65535000.0
            else:  # NaN
                supply_pressure_pa = 0.0
        if not -1.0 <= spool_position <= 1.0:
            m |= 0x10  # SpoolPosition
            if spool_position < -1.0:
                spool_position = -1.0
            elif spool_position > 1.0:
                spool_position = 1.0
            else:  # NaN
                spool_position = 0.0
        if not -32768000.0 <= load_pressure_pa <= 32767000.0:
            m |= 0x20  # LoadPressure
            if load_pressure_pa < -32768000.0:
                load_pressure_pa = -32768000.0
            elif load_pressure_pa > 32767000.0:
                load_pressure_pa = 32767000.0
            else:  # NaN
                load_pressure_pa = 0.0
        b1 = ((counter & 0xf) | (0x10 if bypass_open else 0) | (0x20 if watchdog_tripped else 0) |
              (0x40 if supply_ok else 0))
        _RIG_STATUS_PACK(buf, 0, 0, b1, round(supply_pressure_pa / 1000.0),
                         round(spool_position / 3.05185094759972e-05),
                         round(load_pressure_pa / 1000.0))
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0x7b00 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: RigStatus) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_supply_pressure, r_spool_position, r_load_pressure = _RIG_STATUS_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0x7b00 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        m = 0
        if not -32767 <= r_spool_position <= 32767:
            m |= 0x10  # SpoolPosition
        out.counter = b1 & 0xf
        out.bypass_open = (b1 >> 4) & 0x1
        out.watchdog_tripped = (b1 >> 5) & 0x1
        out.supply_ok = (b1 >> 6) & 0x1
        out.supply_pressure_pa = r_supply_pressure * 1000.0
        out.spool_position = r_spool_position * 3.05185094759972e-05
        out.load_pressure_pa = r_load_pressure * 1000.0
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


class ControllerStatus(Frame):
    """ControllerStatus as decoded: ``counter``, ``range_mask`` and one attribute per signal
    (SI units)."""

    __slots__ = ('active_fault', 'blending', 'jitter_p99_s', 'overrun_count', 'state', 'weight_set')
    FIELDS = ('state', 'active_fault', 'overrun_count', 'blending', 'weight_set', 'jitter_p99_s')
    #: State : 12|4@1+ (1,0) [0|15] ""
    state: int
    #: ActiveFault : 16|8@1+ (1,0) [0|255] ""
    active_fault: int
    #: OverrunCount : 24|16@1+ (1,0) [0|65535] ""
    overrun_count: int
    #: Blending : 40|4@1+ (1,0) [0|15] ""
    blending: int
    #: WeightSet : 44|4@1+ (1,0) [0|15] ""
    weight_set: int
    #: JitterP99 : 48|16@1+ (1e-06,0) [0|0.065535] "s"
    jitter_p99_s: float


class ControllerStatusCodec(Codec):
    """ControllerStatus 0x300, Controller -> Rig, Cyclic every 100 ms."""

    FRAME_ID = 0x300
    NAME = 'ControllerStatus'
    FRAME_TYPE = ControllerStatus
    COUNTER_SIGNAL = 'ControllerStatus_Counter'
    SIGNALS = (
        SignalSpec('state', 'State', 12, 4, False, 1, 0, 15, (0, 1, 2, 3)),
        SignalSpec('active_fault', 'ActiveFault', 16, 8, False, 1, 0, 255,
                   (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16)),
        SignalSpec('overrun_count', 'OverrunCount', 24, 16, False, 1, 0, 65535),
        SignalSpec('blending', 'Blending', 40, 4, False, 1, 0, 15, (0, 1, 2, 3)),
        SignalSpec('weight_set', 'WeightSet', 44, 4, False, 1, 0, 15),
        SignalSpec('jitter_p99_s', 'JitterP99', 48, 16, False, 1e-06, 0.0, 0.065535),
    )

    def encode(self, buf: bytearray | memoryview, counter: int, state: int, active_fault: int,
               overrun_count: int, blending: int, weight_set: int, jitter_p99_s: float) -> int:
        """Counter (modulo 16), signals and CRC into ``buf``; the mask of clamped
        or undefined values (bit i = ``FIELDS[i]``)."""
        m = 0
        if not 0 <= state <= 15:
            m |= 0x1  # State
            state = 0 if state < 0 else 15
        elif state not in {0, 1, 2, 3}:
            m |= 0x1  # State: no VAL_ value
        if not 0 <= active_fault <= 255:
            m |= 0x2  # ActiveFault
            active_fault = 0 if active_fault < 0 else 255
        elif active_fault not in {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16}:
            m |= 0x2  # ActiveFault: no VAL_ value
        if not 0 <= overrun_count <= 65535:
            m |= 0x4  # OverrunCount
            overrun_count = 0 if overrun_count < 0 else 65535
        if not 0 <= blending <= 15:
            m |= 0x8  # Blending
            blending = 0 if blending < 0 else 15
        elif blending not in {0, 1, 2, 3}:
            m |= 0x8  # Blending: no VAL_ value
        if not 0 <= weight_set <= 15:
            m |= 0x10  # WeightSet
            weight_set = 0 if weight_set < 0 else 15
        if not 0.0 <= jitter_p99_s <= 0.065535:
            m |= 0x20  # JitterP99
            if jitter_p99_s < 0.0:
                jitter_p99_s = 0.0
            elif jitter_p99_s > 0.065535:
                jitter_p99_s = 0.065535
            else:  # NaN
                jitter_p99_s = 0.0
        b1 = ((counter & 0xf) | (state << 4))
        b5 = (blending | (weight_set << 4))
        _CONTROLLER_STATUS_PACK(buf, 0, 0, b1, active_fault, overrun_count, b5,
                                round(jitter_p99_s / 1e-06))
        w1, w2, w3, b7 = _CRC_WORDS(buf)
        s = _T2[0x6600 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        buf[0] = _T1[s ^ b7] ^ 0xff
        return m

    def decode(self, data: bytes | bytearray | memoryview, out: ControllerStatus) -> DecodeStatus:
        """Check length and CRC, then fill ``out``; never raises."""
        if len(data) != 8:
            return _BAD_LENGTH
        crc, b1, r_active_fault, r_overrun_count, b5, r_jitter_p99 = _CONTROLLER_STATUS_UNPACK(data)
        w1, w2, w3, b7 = _CRC_WORDS(data)
        s = _T2[0x6600 ^ w1]
        s = _T2[(s << 8) ^ w2]
        s = _T2[(s << 8) ^ w3]
        if crc != _T1[s ^ b7] ^ 0xff:
            return _BAD_CRC
        m = 0
        state = b1 >> 4
        if state not in {0, 1, 2, 3}:
            m |= 0x1  # State
        if r_active_fault not in {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16}:
            m |= 0x2  # ActiveFault
        blending = b5 & 0xf
        if blending not in {0, 1, 2, 3}:
            m |= 0x8  # Blending
        out.counter = b1 & 0xf
        out.state = state
        out.active_fault = r_active_fault
        out.overrun_count = r_overrun_count
        out.blending = blending
        out.weight_set = b5 >> 4
        out.jitter_p99_s = r_jitter_p99 * 1e-06
        out.range_mask = m
        return _OUT_OF_RANGE if m else _OK


VALVE_COMMAND: Final = ValveCommandCodec()
FAULT_REPORT: Final = FaultReportCodec()
SENSOR_DATA: Final = SensorDataCodec()
ROAD_PREVIEW: Final = RoadPreviewCodec()
RIG_STATUS: Final = RigStatusCodec()
CONTROLLER_STATUS: Final = ControllerStatusCodec()
#: frame ID -> codec
CODECS: Final[Mapping[int, Codec]] = {VALVE_COMMAND.FRAME_ID: VALVE_COMMAND,
                                      FAULT_REPORT.FRAME_ID: FAULT_REPORT,
                                      SENSOR_DATA.FRAME_ID: SENSOR_DATA,
                                      ROAD_PREVIEW.FRAME_ID: ROAD_PREVIEW,
                                      RIG_STATUS.FRAME_ID: RIG_STATUS,
                                      CONTROLLER_STATUS.FRAME_ID: CONTROLLER_STATUS}
