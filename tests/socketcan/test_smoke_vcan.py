"""Smoke tests of the SocketCAN environment itself: python-can between two processes,
can-utils (candump / cansend) and python-can's can.logger decoded by cantools with the
project's DBC.  Frames/s and round-trip latency are measured and printed (no timed asserts).
"""

from __future__ import annotations

import shutil
import signal
import statistics
import struct
import subprocess
import time
from pathlib import Path

import can
import cantools
import cantools.logreader
import pytest

from tests.socketcan.peer import ACK_ID, PING_ID, PONG_ID, STOP_ID, STREAM_ID, WINDOW
from tests.socketcan.support import (
    DBC_PATH,
    PYTHON,
    Children,
    counter_gaps,
    frame_crc,
    protect,
    read_candump_log,
    record,
)


def _bus(channel: str, *ids: int) -> can.BusABC:
    filters = [{"can_id": i, "can_mask": 0x7FF} for i in ids] or None
    return can.Bus(interface="socketcan", channel=channel, can_filters=filters)


def _recv_id(bus: can.BusABC, frame_id: int, timeout_s: float) -> can.Message:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        msg = bus.recv(timeout=left)
        if msg is not None and msg.arbitration_id == frame_id:
            return msg
    raise AssertionError(f"no frame 0x{frame_id:03X} within {timeout_s} s")


def test_python_can_two_processes_rtt_and_throughput(channel: str, children: Children) -> None:
    peer = children.python("peer", "-m", "tests.socketcan.peer", "--channel", channel)
    peer.wait_for_output(r"peer ready", timeout_s=30)
    with _bus(channel, PONG_ID, ACK_ID) as bus:
        # round trip: one ping in flight at a time
        rtts = []
        for seq in range(400):
            payload = struct.pack("<II", seq, 0xA5A5A5A5)
            t0 = time.perf_counter()
            bus.send(can.Message(arbitration_id=PING_ID, data=payload, is_extended_id=False))
            reply = _recv_id(bus, PONG_ID, timeout_s=2.0)
            rtts.append(time.perf_counter() - t0)
            assert bytes(reply.data) == payload, "echo changed the frame"
        rtts_ms = sorted(1e3 * r for r in rtts[20:])  # first ones include warm-up
        record("round trip, median", statistics.median(rtts_ms), "ms", "python-can <-> peer")
        record("round trip, p99", rtts_ms[int(0.99 * (len(rtts_ms) - 1))], "ms")

        # throughput: windows of WINDOW frames, each acknowledged before the next (no
        # receive-buffer overrun, so every frame must arrive, in order)
        n_frames = 4 * 1024
        t0 = time.perf_counter()
        for seq in range(n_frames):
            last = seq == n_frames - 1
            data = struct.pack("<IB3x", seq, 1 if last else 0)
            bus.send(can.Message(arbitration_id=STREAM_ID, data=data, is_extended_id=False))
            if (seq + 1) % WINDOW == 0 or last:
                ack = _recv_id(bus, ACK_ID, timeout_s=5.0)
                assert struct.unpack_from("<I", ack.data)[0] == seq
        elapsed = time.perf_counter() - t0
        record("throughput, one way, flow-controlled", n_frames / elapsed, "frames/s",
               f"{n_frames} frames, window {WINDOW}")
        bus.send(can.Message(arbitration_id=STOP_ID, data=b"", is_extended_id=False))
    assert peer.wait(timeout_s=10) == 0
    summary = peer.wait_for_output(r"stream received=(\d+) lost=(\d+) reordered=(\d+)", 1)
    assert (int(summary[1]), int(summary[2]), int(summary[3])) == (n_frames, 0, 0)


def test_candump_sees_python_can_and_cansend_reaches_python_can(
        channel: str, children: Children, tmp_path: Path) -> None:
    assert shutil.which("candump") and shutil.which("cansend"), "can-utils not installed"
    sent = [bytes([i, 0x10 + i, 0xFF, 0, 0, 0, 0, i]) for i in range(5)]
    dump = children.start("candump", ["candump", "-L", "-n", str(len(sent)),
                                      f"{channel},123:7FF"])
    time.sleep(0.5)  # candump has no ready message: give it time to bind
    with _bus(channel, 0x321) as bus:
        for data in sent:
            bus.send(can.Message(arbitration_id=0x123, data=data, is_extended_id=False))
        assert dump.wait(timeout_s=10) == 0
        log = tmp_path / "candump.log"
        log.write_text(dump.output())
        frames = read_candump_log(log)
        assert [(f.channel, f.arbitration_id, f.data) for f in frames] == [
            (channel, 0x123, d) for d in sent]

        subprocess.run(["cansend", channel, "321#DEADBEEF01"], check=True, timeout=10)
        msg = _recv_id(bus, 0x321, timeout_s=5.0)
        assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (
            0x321, bytes.fromhex("DEADBEEF01"), False)


def test_can_logger_capture_decodes_with_the_dbc(
        channel: str, children: Children, tmp_path: Path) -> None:
    db = cantools.database.load_file(str(DBC_PATH))
    sensor = db.get_message_by_name("SensorData")
    log_path = tmp_path / "capture.log"
    logger = children.python("can.logger", "-m", "can.logger", "-i", "socketcan",
                             "-c", channel, "-f", str(log_path))
    logger.wait_for_output(r"Connected to", timeout_s=30)
    time.sleep(0.2)
    readings = [(1e-3 * k, 100.0 - 7.5 * k, 0.25 * k - 1.0) for k in range(20)]
    with _bus(channel) as bus:
        for k, (rattle_m, force_n, accel) in enumerate(readings):
            raw = sensor.encode({"SensorData_CRC": 0, "SensorData_Counter": 0,
                                 "SensorStatus": 0, "Rattlespace": rattle_m,
                                 "LoadCellForce": force_n, "SprungAccel": accel})
            bus.send(can.Message(arbitration_id=sensor.frame_id,
                                 data=protect(sensor.frame_id, raw, k % 16),
                                 is_extended_id=False))
            time.sleep(0.002)
        time.sleep(0.5)
    assert logger.stop(signal.SIGINT) == 0, logger.output()

    # the file is in candump -L format: the independent parser and cantools agree on it
    frames = read_candump_log(log_path)
    assert counter_gaps(frames, sensor.frame_id) == (len(readings), 0, 0)
    assert all(f.data[0] == frame_crc(f.arbitration_id, f.data) for f in frames)
    with open(log_path) as fh:
        parsed = [entry for entry in cantools.logreader.Parser(fh) if entry is not None]
    decoded = [db.decode_message(p.frame_id, p.data) for p in parsed
               if p.frame_id == sensor.frame_id]
    assert len(decoded) == len(readings)
    for sig, (rattle_m, force_n, accel) in zip(decoded, readings, strict=True):
        assert sig["Rattlespace"] == pytest.approx(rattle_m, abs=5e-6)
        assert sig["LoadCellForce"] == pytest.approx(force_n, abs=0.5)
        assert sig["SprungAccel"] == pytest.approx(accel, abs=0.005)
    # and the cantools command line decodes the same capture
    cli = subprocess.run([PYTHON, "-m", "cantools", "decode", "--single-line", str(DBC_PATH)],
                         input=log_path.read_text(), capture_output=True, text=True,
                         timeout=120, check=True)
    lines = [ln for ln in cli.stdout.splitlines() if "SensorData(" in ln]
    assert len(lines) == len(readings), cli.stdout
    assert "LoadCellForce: 100.0 N" in lines[0], lines[0]


def test_error_frames_cross_vcan_between_processes(channel: str, children: Children,
                                                   tmp_path: Path) -> None:
    """Error frames (CAN_ERR_FLAG) written by one process reach another's socket when it
    asks for them: the way the end-to-end tests inject BUS_ERROR / BUS_OFF."""
    err_ids = (0x080, 0x040)  # CAN_ERR_BUSERROR, CAN_ERR_BUSOFF (linux/can/error.h)
    dump = children.start("candump", ["candump", "-L", "-n", str(len(err_ids)),
                                      f"{channel},7FF:7FF,#FFFFFFFF"])
    time.sleep(0.5)
    with _bus(channel) as rx, can.Bus(interface="socketcan", channel=channel) as tx:
        for err in err_ids:
            tx.send(can.Message(arbitration_id=err, is_error_frame=True, data=bytes(8),
                                is_extended_id=False))
        got = []
        deadline = time.monotonic() + 5
        while len(got) < len(err_ids) and time.monotonic() < deadline:
            msg = rx.recv(timeout=0.5)
            if msg is not None and msg.is_error_frame:
                got.append(msg.arbitration_id & 0x1FFFFFFF)
    assert got == list(err_ids)
    assert dump.wait(timeout_s=10) == 0
    log = tmp_path / "err.log"
    log.write_text(dump.output())
    assert [f.arbitration_id for f in read_candump_log(log)] == [0x20000000 | e for e in err_ids]


def test_raw_reader_reads_what_recv_reads(channel: str) -> None:
    """The loop's Message-free frame paths (``rig.bus.raw``) on a real SocketCAN socket:
    the same frames, flags and bytes as python-can's ``recv``, the kernel's receive
    filters applied, and nothing pending reads as 0 without blocking."""
    from rig.bus.core import ROLES, receive_filters
    from rig.bus.raw import (
        FRAME_BUFFER_BYTES,
        SocketcanRawFrames,
        raw_frame_reader,
        raw_frame_writer,
    )
    from rig.bus.socketpair import decode_frame

    frames = [
        can.Message(arbitration_id=0x100, data=bytes(range(8)), is_extended_id=False),
        can.Message(arbitration_id=0x101, data=b"\x01\x02", is_extended_id=False),
        can.Message(arbitration_id=0x123, data=b"\xff", is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDE, data=b"\x05" * 8, is_extended_id=True),
        can.Message(arbitration_id=0x200, is_remote_frame=True, dlc=8, is_extended_id=False),
        can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8),
                    is_extended_id=False),
    ]
    role_ids = set(ROLES["controller"] or ())

    def key(m: can.Message) -> tuple[object, ...]:
        return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_error_frame,
                m.dlc, b"" if m.is_remote_frame else bytes(m.data))

    buf = bytearray(FRAME_BUFFER_BYTES)

    def drain(reader: SocketcanRawFrames, count: int) -> list[tuple[object, ...]]:
        got: list[tuple[object, ...]] = []
        deadline = time.monotonic() + 5
        while len(got) < count and time.monotonic() < deadline:
            n = reader.recv_frame_into(buf)
            if n == 0:
                time.sleep(0.01)
            else:
                got.append(key(decode_frame(bytes(buf[:n]))))
        return got

    with can.Bus(interface="socketcan", channel=channel) as tx, \
            can.Bus(interface="socketcan", channel=channel) as ref, \
            can.Bus(interface="socketcan", channel=channel) as raw_bus, \
            can.Bus(interface="socketcan", channel=channel,
                    can_filters=receive_filters("controller")) as filtered:
        reader, freader = raw_frame_reader(raw_bus), raw_frame_reader(filtered)
        assert isinstance(reader, SocketcanRawFrames)
        assert isinstance(freader, SocketcanRawFrames)
        assert reader.recv_frame_into(buf) == 0
        for msg in frames:
            tx.send(msg)
        want: list[can.Message] = []
        deadline = time.monotonic() + 5
        while len(want) < len(frames) and time.monotonic() < deadline:
            got = ref.recv(timeout=0.5)
            if got is not None:
                want.append(got)
        assert len(want) == len(frames)
        assert drain(reader, len(frames)) == [key(m) for m in want]
        expect = [key(m) for m in want if m.is_error_frame
                  or (not m.is_extended_id and m.arbitration_id in role_ids)]
        assert len(expect) == 4
        assert drain(freader, len(expect)) == expect
        assert freader.recv_frame_into(buf) == 0
        # and out: a struct can_frame as the loop sends it reaches python-can's recv
        writer = raw_frame_writer(raw_bus)
        assert isinstance(writer, SocketcanRawFrames)
        frame = bytearray(16)
        struct.pack_into("=IB", frame, 0, 0x123, 8)
        frame[8:] = bytes(range(10, 18))
        writer.send_frame(frame)
        echo = ref.recv(timeout=2.0)
        assert echo is not None
        assert key(echo) == (0x123, False, False, False, 8, bytes(range(10, 18)))
