"""The loop's Message-free frame paths (``rig.bus.raw``) against its Message paths.

``RigIO.read`` reads a bus that hands over SocketCAN's frame layout (the socket pair
here; SocketCAN in tests/socketcan) into a buffer and decodes in place; any other bus
through ``recv``.  Whatever the frames, both must leave the same trace: the same calls to
the fault monitor, the same frames for the recording, the same held values and road
preview.  ``RigIO.write_*`` send a preallocated ``struct can_frame`` on such a bus, a
``can.Message`` on others: the rig must receive the same frames.  The Message paths are
the reference (python-can's virtual bus).
"""

from __future__ import annotations

import uuid
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from rig.bus.core import CAN_ERR_BUSOFF, CAN_ERR_CRTL, open_bus
from rig.bus.raw import FRAME_BUFFER_BYTES, raw_frame_reader
from rig.bus.socketpair import SocketPairBus, socketpair_wire
from rig.service.hardware import FRAME_LOG_SLOTS, RigIO
from rig.service.road_preview_stream import RoadPreviewStream
from rig.wire.protocol import (
    CONTROLLER_STATUS_ID,
    FAULT_REPORT_ID,
    RIG_STATUS,
    RIG_STATUS_ID,
    ROAD_PREVIEW,
    ROAD_PREVIEW_ID,
    SENSOR_DATA,
    SENSOR_DATA_ID,
    VALVE_COMMAND_ID,
)


class TraceMonitor:
    """The fault monitor's receive-side calls, in order (``sensor_frame`` accepts every
    intact frame whose counter is even, so both branches of the caller run)."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []

    def sensor_frame(self, crc_ok: bool, counter: int, status_bits: int, rattlespace_m: float,
                     force_n: float, accel_mps2: float) -> bool:
        self.calls.append(("sensor", crc_ok, counter, status_bits, rattlespace_m, force_n,
                           accel_mps2))
        return crc_ok and counter % 2 == 0

    def rig_status(self, crc_ok: bool, counter: int, watchdog: bool, supply_ok: bool) -> None:
        self.calls.append(("rig_status", crc_ok, counter, watchdog, supply_ok))

    def bus_error(self, code: Any, detail: int) -> None:
        self.calls.append(("bus_error", code, detail))


class TraceRecorder:
    def __init__(self) -> None:
        self.frames: list[tuple[Any, ...]] = []

    def can_frame(self, t_ns: int, tick: int, arbitration_id: int, data: Any, is_rx: bool,
                  error_frame: bool = False, extended_id: bool = False) -> bool:
        self.frames.append((t_ns, tick, arbitration_id, bytes(data), is_rx, error_frame,
                            extended_id))
        return True


def _sensor(counter: int, rs: float, corrupt: bool) -> can.Message:
    buf = bytearray(8)
    SENSOR_DATA.encode(buf, counter, 0, rs, 100.0 * rs, -rs)
    if corrupt:
        buf[5] ^= 0x10
    return can.Message(arbitration_id=SENSOR_DATA_ID, data=buf, is_extended_id=False)


def _preview(counter: int, v: float, lead: int, sensor_counter: int) -> can.Message:
    buf = bytearray(8)
    ROAD_PREVIEW.encode(buf, counter, 0, v, lead, sensor_counter)
    return can.Message(arbitration_id=ROAD_PREVIEW_ID, data=buf, is_extended_id=False)


def _rig_status(counter: int, watchdog: int) -> can.Message:
    buf = bytearray(8)
    RIG_STATUS.encode(buf, counter, 1, watchdog, 1, 2.0e7, 0.1, 1.0e6)
    return can.Message(arbitration_id=RIG_STATUS_ID, data=buf, is_extended_id=False)


_frames = st.one_of(
    st.builds(_sensor, st.integers(0, 15), st.floats(-0.05, 0.05), st.booleans()),
    st.builds(_preview, st.integers(0, 15), st.floats(-2.0, 2.0), st.integers(0, 300),
              st.integers(0, 15)),
    st.builds(_rig_status, st.integers(0, 15), st.integers(0, 1)),
    # the protocol's IDs with the wrong length, unknown IDs, extended IDs, remote frames
    st.builds(lambda i, d: can.Message(arbitration_id=i, data=d, is_extended_id=False),
              st.sampled_from([SENSOR_DATA_ID, ROAD_PREVIEW_ID, RIG_STATUS_ID, 0x0, 0x7FF]),
              st.binary(max_size=8)),
    st.builds(lambda i, d: can.Message(arbitration_id=i, data=d, is_extended_id=True),
              st.sampled_from([SENSOR_DATA_ID, 0x1FFFFFFF]), st.binary(max_size=8)),
    st.builds(lambda i: can.Message(arbitration_id=i, is_remote_frame=True, dlc=8,
                                    is_extended_id=False),
              st.sampled_from([SENSOR_DATA_ID, RIG_STATUS_ID])),
    st.builds(lambda cls, d1: can.Message(arbitration_id=cls, is_error_frame=True,
                                          data=bytes([0, d1, 0, 0, 0, 0, 0, 0]),
                                          is_extended_id=False),
              st.sampled_from([CAN_ERR_BUSOFF, CAN_ERR_CRTL, 0x001]), st.sampled_from([0x40, 4])),
    # a CAN FD frame of the sensor's ID: not the protocol's frame, its length is wrong
    st.builds(lambda d: can.Message(arbitration_id=SENSOR_DATA_ID, data=d, is_fd=True,
                                    is_extended_id=False),
              st.binary(min_size=12, max_size=12)),
)


def _io(bus: can.BusABC) -> tuple[RigIO, TraceMonitor, TraceRecorder]:
    mon, rec = TraceMonitor(), TraceRecorder()
    io = RigIO(bus, mon, rec, lambda t, k, d: None, lambda e: None)  # type: ignore[arg-type]
    io.preview = RoadPreviewStream(20, capacity=512)
    return io, mon, rec


def _state(io: RigIO) -> tuple[Any, ...]:
    pv = io.preview
    assert pv is not None
    return (io.rattlespace_m, io.force_meas_n, io.accel_mps2, io.sensor_counter,
            io.rig_status_seen, io.rig_watchdog_tripped, io.rx_frames, pv.rig_tick,
            pv.run_start, pv.run_end, pv.lead, pv.breaks, pv.lost_reason, pv.ring.tobytes())


@settings(max_examples=60, deadline=None)
@given(ticks=st.lists(st.lists(_frames, max_size=6), min_size=1, max_size=12))
def test_raw_path_leaves_the_trace_of_the_message_path(ticks: list[list[can.Message]]) -> None:
    channel = f"raw-{uuid.uuid4().hex}"
    v_ctl = open_bus(default_config().can, interface="virtual", channel=channel)
    v_rig = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    a, b = socketpair_wire()
    s_rig, s_ctl = SocketPairBus(a, fd=True), SocketPairBus(b, fd=True)
    try:
        ref, ref_mon, ref_rec = _io(v_ctl)
        raw, raw_mon, raw_rec = _io(s_ctl)
        assert ref._raw is None and raw._raw is s_ctl
        for k, frames in enumerate(ticks):
            for msg in frames:
                v_rig.send(msg)
                s_rig.send(msg)
            ref.read(1000 * k, k)
            raw.read(1000 * k, k)
            ref.record_frames()
            raw.record_frames()
            assert raw_mon.calls == ref_mon.calls
            assert raw_rec.frames == ref_rec.frames
            assert _state(raw) == _state(ref)
    finally:
        for bus in (v_ctl, v_rig, s_rig, s_ctl):
            bus.shutdown()


def test_frame_log_overflow_hands_frames_over_in_order() -> None:
    a, b = socketpair_wire()
    rig, ctl = SocketPairBus(a), SocketPairBus(b)
    try:
        io, _mon, rec = _io(ctl)
        sent = [_sensor(k % 16, 0.001 * k, False) for k in range(FRAME_LOG_SLOTS + 5)]
        for msg in sent:
            rig.send(msg)
        io.read(7, 3)
        io.record_frames()
        assert [f[3] for f in rec.frames] == [bytes(m.data) for m in sent]
        assert all(f[:3] == (7, 3, SENSOR_DATA_ID) and f[4] for f in rec.frames)
    finally:
        rig.shutdown()
        ctl.shutdown()


def test_which_buses_are_read_in_place() -> None:
    a, b = socketpair_wire()
    plain = SocketPairBus(a)
    filtered = SocketPairBus(b, can_filters=[{"can_id": SENSOR_DATA_ID, "can_mask": 0x7FF}])
    virtual = can.Bus(interface="virtual", channel=f"raw-{uuid.uuid4().hex}")
    try:
        assert raw_frame_reader(plain) is plain
        assert raw_frame_reader(filtered) is None       # its recv applies the filters
        assert raw_frame_reader(virtual) is None
    finally:
        for bus in (plain, filtered, virtual):
            bus.shutdown()


@pytest.mark.parametrize("size", [1, 15, 17, 71])
def test_a_datagram_of_another_size_is_a_bus_error(size: int) -> None:
    a, b = socketpair_wire()
    ctl = SocketPairBus(b)
    try:
        buf = bytearray(FRAME_BUFFER_BYTES)
        a.send(bytes(size))
        with pytest.raises(can.CanOperationError, match=f"frame of {size} bytes"):
            ctl.recv_frame_into(buf)
        a.send(np.zeros(2, dtype=np.uint8).tobytes())
        io, mon, rec = _io(ctl)
        io.read(0, 0)
        assert [c[0] for c in mon.calls] == ["bus_error"]
        assert rec.frames == []
    finally:
        a.close()
        ctl.shutdown()


_writes = st.lists(st.one_of(
    st.tuples(st.just("valve"), st.integers(0, 1), st.integers(0, 3),
              st.floats(-1.5, 1.5), st.floats(-2e4, 2e4)),
    st.tuples(st.just("fault"), st.integers(0, 3), st.integers(0, 40),
              st.integers(-5, 2**33), st.integers(0, 255)),
    st.tuples(st.just("status"), st.integers(0, 3), st.integers(0, 40),
              st.integers(0, 2**17), st.integers(0, 3), st.integers(0, 20),
              st.floats(0.0, 0.1)),
), min_size=1, max_size=20)


def _write(io: RigIO, k: int, w: tuple[Any, ...]) -> bool:
    if w[0] == "valve":
        return io.write_valve(k, k, *w[1:])
    if w[0] == "fault":
        return io.write_fault_report(k, k, *w[1:])
    return io.write_status(k, k, *w[1:])


@settings(max_examples=40, deadline=None)
@given(writes=_writes)
def test_raw_send_puts_the_frames_of_the_message_path_on_the_wire(
        writes: list[tuple[Any, ...]]) -> None:
    channel = f"raw-{uuid.uuid4().hex}"
    v_ctl = open_bus(default_config().can, interface="virtual", channel=channel)
    v_rig = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    a, b = socketpair_wire()
    s_rig, s_ctl = SocketPairBus(a), SocketPairBus(b)
    try:
        ref, _, ref_rec = _io(v_ctl)
        raw, _, raw_rec = _io(s_ctl)
        assert ref._raw_tx is None and raw._raw_tx is s_ctl
        for k, w in enumerate(writes):
            assert _write(ref, k, w) and _write(raw, k, w)
        ref.record_frames()
        raw.record_frames()
        assert raw_rec.frames == ref_rec.frames
        assert {f[2] for f in ref_rec.frames} <= {VALVE_COMMAND_ID, FAULT_REPORT_ID,
                                                  CONTROLLER_STATUS_ID}

        def wire(bus: can.BusABC) -> list[tuple[int, bool, bool, bytes]]:
            out = []
            while (m := bus.recv(0.0)) is not None:
                out.append((m.arbitration_id, m.is_extended_id, m.is_fd, bytes(m.data)))
            return out

        assert wire(s_rig) == wire(v_rig)
        assert raw.tx_frames == ref.tx_frames == len(writes)
    finally:
        for bus in (v_ctl, v_rig, s_rig, s_ctl):
            bus.shutdown()


def test_raw_send_to_a_closed_peer_is_a_bus_error_and_a_note() -> None:
    a, b = socketpair_wire()
    ctl = SocketPairBus(b)
    notes: list[dict[str, Any]] = []
    mon, rec = TraceMonitor(), TraceRecorder()
    io = RigIO(ctl, mon, rec, lambda t, k, d: notes.append(d),  # type: ignore[arg-type]
               lambda e: None)
    try:
        a.close()
        assert not io.write_valve(5, 5, 1, 2, 0.1, 10.0)
        assert [c[0] for c in mon.calls] == ["bus_error"]
        assert notes[0]["bus_exception"] == "send"
        assert notes[0]["arbitration_id"] == VALVE_COMMAND_ID
        assert io.tx_errors == 1 and io.tx_frames == 0
        io.record_frames()
        assert rec.frames == []
    finally:
        ctl.shutdown()
