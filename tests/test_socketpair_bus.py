"""The socket-pair CAN wire (rig.bus.socketpair): SocketCAN's frame layout (checked against
python-can's own SocketCAN packer), order, filters while draining, overflow, a vanished
peer, timeouts; and the control loop running on it."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator

import can
import pytest
from can.interfaces.socketcan.socketcan import build_can_frame, dissect_can_frame
from hypothesis import given, settings
from hypothesis import strategies as st

from rig.bus.core import classify_bus_exception
from rig.bus.socketpair import (
    CAN_MTU,
    CANFD_MTU,
    SocketPairBus,
    decode_frame,
    encode_frame,
    socketpair_wire,
)
from rig.wire.protocol import FaultCode

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


@pytest.fixture
def pair() -> Iterator[tuple[SocketPairBus, SocketPairBus]]:
    a, b = socketpair_wire()
    buses = (SocketPairBus(a), SocketPairBus(b, fd=True))
    yield buses
    for bus in buses:
        bus.shutdown()


@st.composite
def messages(draw: st.DrawFn, fd: bool | None = None) -> can.Message:
    is_fd = draw(st.booleans()) if fd is None else fd
    extended = draw(st.booleans())
    arb = draw(st.integers(0, 0x1FFFFFFF if extended else 0x7FF))
    if is_fd:
        length = draw(st.sampled_from(FD_LENGTHS))
        return can.Message(arbitration_id=arb, is_extended_id=extended, is_fd=True,
                           data=draw(st.binary(min_size=length, max_size=length)),
                           bitrate_switch=draw(st.booleans()),
                           error_state_indicator=draw(st.booleans()))
    kind = draw(st.sampled_from(["data", "remote", "error"]))
    if kind == "remote":
        return can.Message(arbitration_id=arb, is_extended_id=extended,
                           is_remote_frame=True, dlc=draw(st.integers(0, 8)))
    return can.Message(arbitration_id=arb, is_extended_id=extended,
                       is_error_frame=kind == "error", data=draw(st.binary(max_size=8)))


def same_frame(a: can.Message, b: can.Message) -> bool:
    return (a.arbitration_id == b.arbitration_id and a.is_extended_id == b.is_extended_id
            and a.is_remote_frame == b.is_remote_frame and a.is_error_frame == b.is_error_frame
            and a.is_fd == b.is_fd and a.dlc == b.dlc
            and (a.is_remote_frame or bytes(a.data) == bytes(b.data))
            and (not a.is_fd or (a.bitrate_switch == b.bitrate_switch
                                 and a.error_state_indicator == b.error_state_indicator)))


@given(messages())
def test_frame_layout_is_socketcans(msg: can.Message) -> None:
    """Our encoder and python-can's SocketCAN packer agree both ways (an independent
    implementation of struct can_frame / canfd_frame)."""
    ours = encode_frame(msg)
    assert len(ours) == (CANFD_MTU if msg.is_fd else CAN_MTU)
    # python-can's decoder reads ours ...
    can_id, length, flags, data = dissect_can_frame(ours)
    ref = build_can_frame(msg)
    ref_id, ref_len, ref_flags, ref_data = dissect_can_frame(ref)
    assert (can_id, length, data) == (ref_id, ref_len, ref_data)
    assert flags & 0x03 == ref_flags & 0x03            # BRS / ESI
    # ... and ours reads python-can's
    assert same_frame(decode_frame(ref), msg)
    assert same_frame(decode_frame(ours), msg)


@settings(max_examples=50, deadline=None)
@given(st.lists(messages(), min_size=1, max_size=40))
def test_frames_arrive_in_order_and_intact(msgs: list[can.Message]) -> None:
    a, b = socketpair_wire()
    tx, rx = SocketPairBus(a, fd=True), SocketPairBus(b)
    try:
        for m in msgs:
            tx.send(m)
        got = [rx.recv(0.0) for _ in msgs]
        assert rx.recv(0.0) is None
        assert all(g is not None and same_frame(g, m) and g.is_rx
                   for g, m in zip(got, msgs, strict=True))
        assert tx.sent == len(msgs) and rx.received == len(msgs) and tx.overflows == 0
    finally:
        tx.shutdown()
        rx.shutdown()


def test_fd_frame_refused_on_a_classic_bus(pair: tuple[SocketPairBus, SocketPairBus]) -> None:
    a, _ = pair
    with pytest.raises(can.CanOperationError, match="CAN FD"):
        a.send(can.Message(arbitration_id=1, is_fd=True, data=bytes(12)))


def test_filters_skip_queued_frames_like_kernel_filters() -> None:
    """recv(timeout=0) returns the matching frame queued behind non-matching ones
    (python-can's software filtering of the virtual bus returns None there)."""
    a, b = socketpair_wire()
    tx = SocketPairBus(a)
    rx = SocketPairBus(b, can_filters=[{"can_id": 0x100, "can_mask": 0x7FF,
                                        "extended": False}])
    try:
        for arb in (0x080, 0x081, 0x100, 0x082, 0x100):
            tx.send(can.Message(arbitration_id=arb, is_extended_id=False, data=b"\x01"))
        got = [rx.recv(0.0), rx.recv(0.0), rx.recv(0.0)]
        assert [m.arbitration_id if m else None for m in got] == [0x100, 0x100, None]
    finally:
        tx.shutdown()
        rx.shutdown()


def test_full_peer_queue_loses_frames_without_blocking_the_sender(
        pair: tuple[SocketPairBus, SocketPairBus]) -> None:
    """Like a SocketCAN receiver that overflows: the sender is neither blocked nor told,
    the reader gets the oldest frames and sees the gap in the data."""
    a, b = pair
    n = 20_000
    for i in range(n):
        a.send(can.Message(arbitration_id=0x100, is_extended_id=False,
                           data=struct.pack("<I", i)))
    assert a.overflows > 0 and a.sent + a.overflows == n
    got = []
    while (m := b.recv(0.0)) is not None:
        got.append(struct.unpack("<I", m.data)[0])
    assert got == list(range(a.sent))


def test_peer_gone_is_a_bus_error_both_ways() -> None:
    a, b = socketpair_wire()
    ours, theirs = SocketPairBus(a), SocketPairBus(b)
    theirs.send(can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x01"))
    theirs.shutdown()
    assert ours.recv(0.0) is not None             # what was sent before still arrives
    for action in (lambda: ours.recv(0.0),
                   lambda: ours.send(can.Message(arbitration_id=1, is_extended_id=False))):
        with pytest.raises(can.CanOperationError) as err:
            action()
        assert classify_bus_exception(err.value) is FaultCode.BUS_ERROR
    ours.shutdown()
    ours.shutdown()                                # idempotent
    with pytest.raises(can.CanOperationError, match="shut down"):
        ours.recv(0.0)


def test_recv_waits_for_a_frame_or_the_timeout(pair: tuple[SocketPairBus, SocketPairBus]
                                               ) -> None:
    a, b = pair
    assert b.recv(0.02) is None
    threading.Timer(0.05, lambda: a.send(can.Message(arbitration_id=7, is_extended_id=False,
                                                     data=b"\x07"))).start()
    t0 = time.monotonic()
    got = b.recv(10.0)
    assert got is not None and got.arbitration_id == 7
    assert time.monotonic() - t0 < 9.0             # woken by the frame, not the timeout


def test_from_inherited_fileno_and_wrong_socket_type() -> None:
    import socket

    a, b = socketpair_wire()
    bus = SocketPairBus(fileno=a.detach())
    peer = SocketPairBus(b)
    peer.send(can.Message(arbitration_id=3, is_extended_id=False, data=b"\x03"))
    assert bus.recv(1.0) is not None
    bus.shutdown()
    peer.shutdown()
    s1, s2 = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with pytest.raises(ValueError, match="SOCK_SEQPACKET"):
        SocketPairBus(s1)
    s1.close()
    s2.close()
