"""The controller's hardware interface (ros2_control's read / write): the CAN frames of the
rig in, the valve command, fault report and heartbeat out.

:meth:`RigIO.read` drains the bus and hands every SensorData / RigStatus to the fault
monitor's checks (CRC, rolling counter, ranges, status bits); the last good values are
held in attributes for the update.  On a bus that hands over SocketCAN's frame layout
(``rig.bus.raw``: the rig's SocketCAN, the emulated rig's socket pair) a frame is read
into a preallocated buffer and decoded in place, with no ``can.Message``; any other bus
is read with ``recv``, and both paths end in the same per-frame code.  The ``write_*``
methods encode into preallocated frames (``struct can_frame`` on those buses, a
``can.Message`` on others) and send without blocking.  Receive and send
errors are bus faults for the monitor and ``note`` events for the recording; nothing
here raises for a bad frame.

Recording a frame costs the loop a ``struct.pack_into`` and a copy into the recorder's
batch; it is not on the way from the sensor frame to the valve command.  The frames of a
tick are noted in a preallocated log as they come and go (a received message by
reference: a bus returns a new one per ``recv``; the bytes of a frame read in place, and
of a sent one, copied, since the buffer is read into and the preallocated message
encoded again) and handed to the recorder by
:meth:`RigIO.record_frames`, which the loop calls after the tick's frames are out and
before any other item of the recording (an event, the tick record), so that the
recording's items and their order are what they would be if each frame were recorded as
it came.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import can

from rig.bus.core import classify_bus_exception, classify_error_frame, errno_of, make_tx_message
from rig.bus.raw import FRAME_BUFFER_BYTES, raw_frame_reader, raw_frame_writer
from rig.bus.socketpair import CAN_MTU, CAN_SFF_MASK, decode_frame, encode_frame
from rig.service.road_preview_stream import RoadPreviewStream
from rig.service.safety import DETAIL_RECV, DETAIL_SEND, FaultMonitor
from rig.service.seams import Recorder
from rig.wire.protocol import (
    CONTROLLER_STATUS,
    FAULT_REPORT,
    FRAME_LENGTH,
    RIG_STATUS,
    RIG_STATUS_ID,
    ROAD_PREVIEW,
    ROAD_PREVIEW_ID,
    SENSOR_DATA,
    SENSOR_DATA_ID,
    VALVE_COMMAND,
    DecodeStatus,
    FaultCode,
    RigStatus,
    RoadPreview,
    SensorData,
)
from rig.wire_modes import to_wire

__all__ = ["FRAME_LOG_SLOTS", "RigIO", "bus_exception_note"]

#: frames noted per tick before the log is handed to the recorder early (a tick has 4-6)
FRAME_LOG_SLOTS = 64
_MAX_DATA = 64             # a CAN FD frame's bytes

_OK = DecodeStatus.OK
_OUT_OF_RANGE = DecodeStatus.OUT_OF_RANGE
_NONE = FaultCode.NONE
_RAW_HEAD = struct.Struct("=IB")     # struct can_frame: can_id (with its flags), len

#: ``note(t_ns, tick, detail)``: a ``note`` event for the recording
Note = Callable[[int, int, dict[str, Any]], None]


class _TxFrame:
    """One frame the loop sends, preallocated and encoded in place every time: a
    ``can.Message`` for ``bus.send``, or SocketCAN's ``struct can_frame`` for a
    :class:`rig.bus.raw.RawFrameWriter` (``raw``).  ``data`` is where the encoder writes:
    the Message's 8 data bytes, or the frame's."""

    __slots__ = ("data", "frame", "frame_id", "msg")

    def __init__(self, frame_id: int, raw: bool) -> None:
        self.frame_id = frame_id
        self.msg = make_tx_message(frame_id)
        self.frame = bytearray(encode_frame(self.msg))
        self.data: bytearray | memoryview = (memoryview(self.frame)[8:8 + FRAME_LENGTH]
                                             if raw else self.msg.data)


def bus_exception_note(where: str, exc: BaseException) -> dict[str, Any]:
    """The ``note`` event detail of a failed recv / send (replay raises it again)."""
    return {"bus_exception": where, "type": type(exc).__name__, "error": str(exc),
            "errno": errno_of(exc)}


class RigIO:
    """Frames in and out on one bus for the control loop."""

    def __init__(self, bus: can.BusABC, monitor: FaultMonitor, recorder: Recorder | None,
                 note: Note, on_output_error: Callable[[Exception], None]) -> None:
        self.bus = bus
        self.monitor = monitor
        self.recorder = recorder
        self._note = note
        self._on_output_error = on_output_error
        # frames out: through a RawFrameWriter where the bus has one (rig.bus.raw)
        self._raw_tx = raw_frame_writer(bus)
        raw_tx = self._raw_tx is not None
        self._valve_tx = _TxFrame(VALVE_COMMAND.frame_id, raw_tx)
        self._fault_tx = _TxFrame(FAULT_REPORT.frame_id, raw_tx)
        self._status_tx = _TxFrame(CONTROLLER_STATUS.frame_id, raw_tx)
        self._sd = SensorData()
        self._rs = RigStatus()
        self._rp = RoadPreview()
        # the Message-free receive path (rig.bus.raw), where the bus has one: the frame
        # is read into _rx_buf and its data bytes are one of the views _rx_data[length]
        self._raw = raw_frame_reader(bus)
        self._rx_buf = bytearray(FRAME_BUFFER_BYTES)
        self._rx_view = memoryview(self._rx_buf)
        self._rx_data = [self._rx_view[8:8 + k] for k in range(9)]
        #: the road ahead from RoadPreview frames (set by the loop when the road preview
        #: is on; None: the frames are counted and recorded, not decoded)
        self.preview: RoadPreviewStream | None = None
        # the frame log (see the module docstring): per slot the time, tick, message
        # (received) or None (sent: id, flags and bytes copied into the slot)
        self._log_n = 0
        self._log_t = [0] * FRAME_LOG_SLOTS
        self._log_tick = [0] * FRAME_LOG_SLOTS
        self._log_msg: list[can.Message | None] = [None] * FRAME_LOG_SLOTS
        self._log_rx = [False] * FRAME_LOG_SLOTS
        self._log_id = [0] * FRAME_LOG_SLOTS
        self._log_dlc = [0] * FRAME_LOG_SLOTS
        self._log_data = [memoryview(bytearray(_MAX_DATA)) for _ in range(FRAME_LOG_SLOTS)]
        self.reset()

    def reset(self) -> None:
        """Counters and held values to their start-up values."""
        self._tx_valve = 0
        self._tx_fault = 0
        self._tx_status = 0
        self.rattlespace_m = 0.0
        self.force_meas_n = 0.0
        self.accel_mps2 = 0.0
        self.sensor_counter = 0
        self.rig_bypass_open = 1
        self.rig_watchdog_tripped = 0
        self.rig_supply_ok = 1
        self.rig_status_seen = False
        self.rx_frames = 0
        self.tx_frames = 0
        self.tx_errors = 0

    # ------------------------------------------------------------------ read
    def read(self, now_ns: int, tick: int) -> None:
        """Drain the bus: decode and check every frame waiting (never blocks)."""
        if self._raw is not None:
            self._read_raw(now_ns, tick)
            return
        bus = self.bus
        while True:
            try:
                msg = bus.recv(0.0)
            except (can.CanError, OSError) as exc:
                self._recv_failed(now_ns, tick, exc)
                return
            if msg is None:
                return
            self._message(msg, now_ns, tick)

    def _read_raw(self, now_ns: int, tick: int) -> None:
        """:meth:`read` on a bus with a :class:`rig.bus.raw.RawFrameReader`: a standard
        classic data frame (every frame of the rig's protocol) is decoded from the
        receive buffer in place; any other frame (error, extended, remote, CAN FD) is
        made a ``can.Message`` and takes the Message path."""
        assert self._raw is not None
        recv_into = self._raw.recv_frame_into
        buf = self._rx_buf
        views = self._rx_data
        rec = self.recorder
        while True:
            try:
                n = recv_into(buf)
            except (can.CanError, OSError) as exc:
                self._recv_failed(now_ns, tick, exc)
                return
            if n == 0:
                return
            if n == CAN_MTU:
                can_id, length = _RAW_HEAD.unpack_from(buf)
                if can_id <= CAN_SFF_MASK:
                    data = views[length if length < 8 else 8]
                    self.rx_frames += 1
                    if rec is not None:
                        self._log_bytes(self._log_slot(now_ns, tick), True, can_id, data)
                    self._data_frame(can_id, data)
                    continue
            self._message(decode_frame(self._rx_view[:n]), now_ns, tick)

    def _recv_failed(self, now_ns: int, tick: int, exc: BaseException) -> None:
        self.monitor.bus_error(classify_bus_exception(exc), DETAIL_RECV)
        self._note(now_ns, tick, bus_exception_note("recv", exc))

    def _message(self, msg: can.Message, now_ns: int, tick: int) -> None:
        """One received frame as a ``can.Message``: noted for the recording, an error
        frame to the monitor, a standard data frame to :meth:`_data_frame`."""
        self.rx_frames += 1
        if self.recorder is not None:
            self._log_msg[self._log_slot(now_ns, tick)] = msg
        if msg.is_error_frame:
            code = classify_error_frame(msg)
            if code is not _NONE:
                self.monitor.bus_error(code, msg.arbitration_id & 0xFF)
            return
        if not msg.is_extended_id:
            self._data_frame(msg.arbitration_id, msg.data)

    def _data_frame(self, fid: int, data: bytes | bytearray | memoryview) -> None:
        """A standard-ID data frame's bytes: SensorData, RoadPreview and RigStatus are
        decoded and checked, every other ID is ignored."""
        mon = self.monitor
        if fid == SENSOR_DATA_ID:
            sd = self._sd
            st = SENSOR_DATA.decode(data, sd)
            if st is _OK:
                if mon.sensor_frame(True, sd.counter, sd.sensor_status, sd.rattlespace_m,
                                    sd.load_cell_force_n, sd.sprung_accel_mps2):
                    self.rattlespace_m = sd.rattlespace_m
                    self.force_meas_n = sd.load_cell_force_n
                    self.accel_mps2 = sd.sprung_accel_mps2
                    self.sensor_counter = sd.counter
                    if self.preview is not None:
                        self.preview.sensor(sd.counter)
            else:
                mon.sensor_frame(False, 0, 0, 0.0, 0.0, 0.0)
        elif fid == ROAD_PREVIEW_ID:
            pv = self.preview
            if pv is not None:
                rp = self._rp
                good = ROAD_PREVIEW.decode(data, rp) is _OK
                pv.frame(good, rp.preview_status, rp.road_velocity_mps, rp.preview_lead,
                         rp.preview_sensor_counter)
        elif fid == RIG_STATUS_ID:
            rs = self._rs
            st = RIG_STATUS.decode(data, rs)
            if st is _OK or st is _OUT_OF_RANGE:
                self.rig_status_seen = True
                self.rig_bypass_open = rs.bypass_open
                self.rig_watchdog_tripped = rs.watchdog_tripped
                self.rig_supply_ok = rs.supply_ok
                mon.rig_status(True, rs.counter, bool(rs.watchdog_tripped),
                               bool(rs.supply_ok))
            else:
                mon.rig_status(False, 0, False, True)

    # ------------------------------------------------------------------ write
    def _send(self, tx: _TxFrame, now_ns: int, tick: int) -> bool:
        try:
            if self._raw_tx is not None:
                self._raw_tx.send_frame(tx.frame)
            else:
                self.bus.send(tx.msg, 0.0)
        except (can.CanError, OSError) as exc:
            self.tx_errors += 1
            self.monitor.bus_error(classify_bus_exception(exc), DETAIL_SEND)
            self._note(now_ns, tick, {**bus_exception_note("send", exc),
                                      "arbitration_id": tx.frame_id})
            return False
        self.tx_frames += 1
        if self.recorder is not None:
            self._log_bytes(self._log_slot(now_ns, tick), False, tx.frame_id, tx.data)
        return True

    def _log_slot(self, now_ns: int, tick: int) -> int:
        """The frame log's next slot, for a frame at ``now_ns`` / ``tick`` (a full log
        is handed to the recorder first)."""
        n = self._log_n
        if n == FRAME_LOG_SLOTS:
            self.record_frames()
            n = 0
        self._log_t[n] = now_ns
        self._log_tick[n] = tick
        self._log_n = n + 1
        return n

    def _log_bytes(self, n: int, is_rx: bool, frame_id: int,
                   data: bytearray | memoryview) -> None:
        """Slot ``n`` holds a copy of a frame's bytes (a frame read in place or sent)."""
        self._log_msg[n] = None
        self._log_rx[n] = is_rx
        self._log_id[n] = frame_id
        dlc = len(data)
        self._log_dlc[n] = dlc
        self._log_data[n][:dlc] = data

    def record_frames(self) -> None:
        """Hand the frames noted since the last call to the recorder, in the order they
        came and went (the loop: after the tick's frames are out, and before any other
        item it records).  A recorder that raises is counted, never raised."""
        n = self._log_n
        if n == 0:
            return
        self._log_n = 0
        rec = self.recorder
        msgs = self._log_msg
        for i in range(n):
            msg = msgs[i]
            msgs[i] = None
            if rec is None:
                continue
            try:
                if msg is not None:
                    rec.can_frame(self._log_t[i], self._log_tick[i], msg.arbitration_id,
                                  msg.data, True, msg.is_error_frame, msg.is_extended_id)
                else:
                    rec.can_frame(self._log_t[i], self._log_tick[i], self._log_id[i],
                                  self._log_data[i][:self._log_dlc[i]], self._log_rx[i],
                                  False, False)
            except Exception as exc:
                self._on_output_error(exc)

    def write_valve(self, now_ns: int, tick: int, enable: int, lifecycle: int, spool: float,
                    force_ref_n: float) -> bool:
        """ValveCommand (echoing the last good SensorData counter); False: not sent."""
        tx = self._valve_tx
        VALVE_COMMAND.encode(tx.data, self._tx_valve, enable, lifecycle, spool, force_ref_n,
                             self.sensor_counter)
        self._tx_valve += 1
        return self._send(tx, now_ns, tick)

    def write_fault_report(self, now_ns: int, tick: int, lifecycle: int, code: int,
                           fault_tick: int, detail: int) -> bool:
        """FaultReport (``fault_tick`` taken modulo 2**32 by the codec)."""
        tx = self._fault_tx
        FAULT_REPORT.encode(tx.data, self._tx_fault, lifecycle, code, max(fault_tick, 0),
                            detail)
        self._tx_fault += 1
        return self._send(tx, now_ns, tick)

    def write_status(self, now_ns: int, tick: int, lifecycle: int, active_fault: int,
                     overruns: int, blending: int, weight_set: int,
                     jitter_p99_s: float) -> bool:
        """ControllerStatus heartbeat (``blending``: the controller's mode code, sent as
        the DBC's value, ``rig.wire_modes``)."""
        tx = self._status_tx
        CONTROLLER_STATUS.encode(tx.data, self._tx_status, lifecycle, active_fault,
                                 overruns & 0xFFFF, to_wire(blending), weight_set & 0xF,
                                 min(jitter_p99_s, 0.065535))
        self._tx_status += 1
        return self._send(tx, now_ns, tick)
