"""A point-to-point CAN "wire" between two processes: a ``can.BusABC`` over a socket pair.

``rig demo``, the loop benchmark and the tests run the emulated rig in a process of its
own, as on the bench where ``rig hil`` and ``rig run`` share a vcan/can interface.  This
kernel (and a container without ``--network host``) has no SocketCAN, so the two
processes talk over one ``socket.socketpair(AF_UNIX, SOCK_SEQPACKET)``:

- one datagram per frame, in SocketCAN's own layout (``struct can_frame``, 16 bytes;
  ``struct canfd_frame``, 72 bytes, when ``fd``), the flags in the CAN ID's top bits;
- the kernel wakes the reader (no polling, no lock shared between the processes), keeps
  the frames in order and bounds the queue (about 200 frames with the default socket
  buffer: a fifth of a second at 1 kHz);
- a full queue behaves like a SocketCAN receiver that overflows: the frame is lost for
  the peer, the sender is not blocked and not told (counted in :attr:`overflows`);
- a peer that closed its end (or died) makes every ``recv`` and ``send`` raise
  ``can.CanOperationError`` with ``error_code`` ECONNRESET / EPIPE, which
  :func:`rig.bus.core.classify_bus_exception` maps to ``BUS_ERROR`` (on a real bus a missing
  node shows up as missing acknowledgements, not as bus-off);
- receive filters (``can_filters``) are applied while draining, like SocketCAN's kernel
  filters: ``recv(timeout=0)`` skips non-matching frames instead of returning None at
  the first one (python-can's software filtering does the latter).

Why not a python-can interface: ``virtual`` lives inside one process; ``udp_multicast``
sends to a multicast group (not allowed here, and it leaves the host's loopback);
``socketcand`` needs a daemon on a real CAN interface; ``serial``/``slcan`` over a pty
would add a line discipline and byte stuffing to every frame.  A socket pair needs no
address, no port and no network namespace (it works under ``podman run --network none``).

The frames carry no sender time: ``Message.timestamp`` is the receive time
(``time.time()``), as with SocketCAN without hardware time stamps.
"""

from __future__ import annotations

import contextlib
import errno
import select
import socket
import struct
import time
from typing import Any, Final

import can

__all__ = ["CANFD_MTU", "CAN_MTU", "CAN_SFF_MASK", "SocketPairBus", "check_frame_size",
           "decode_frame", "encode_frame", "socketpair_wire"]

CAN_MTU: Final = 16         # sizeof(struct can_frame)
CANFD_MTU: Final = 72       # sizeof(struct canfd_frame)
CAN_EFF_FLAG: Final = 0x80000000
CAN_RTR_FLAG: Final = 0x40000000
CAN_ERR_FLAG: Final = 0x20000000
CAN_EFF_MASK: Final = 0x1FFFFFFF
CANFD_BRS: Final = 0x01
CANFD_ESI: Final = 0x02
CANFD_FDF: Final = 0x04     # set in every CAN FD frame by Linux since CAN XL
_HEAD: Final = struct.Struct("=IBBBB")    # can_id, len, flags / pad, res0, len8_dlc / res1
_FD_LENGTHS: Final = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_CLASSIC: Final = struct.Struct("=IB3x8s")   # can_id, len, data (struct can_frame)
CAN_SFF_MASK: Final = 0x7FF   # a standard (11-bit) ID, no flag bit set



def socketpair_wire() -> tuple[socket.socket, socket.socket]:
    """A connected pair of AF_UNIX SOCK_SEQPACKET sockets (not inherited by children
    unless passed explicitly, e.g. ``subprocess.Popen(pass_fds=...)``)."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    return a, b


def check_frame_size(n: int, where: str) -> None:
    """Raise ``can.CanOperationError`` (EMSGSIZE) unless ``n`` bytes read from ``where``
    are a CAN frame: ``CAN_MTU`` or ``CANFD_MTU``."""
    if n != CAN_MTU and n != CANFD_MTU:
        raise can.CanOperationError(f"{where}: frame of {n} bytes: a CAN frame has "
                                    f"{CAN_MTU} or {CANFD_MTU}", error_code=errno.EMSGSIZE)


def encode_frame(msg: can.Message) -> bytes:
    """``msg`` as SocketCAN's ``struct can_frame`` (or ``canfd_frame`` when ``is_fd``)."""
    can_id = msg.arbitration_id
    if msg.is_extended_id:
        can_id = (can_id & CAN_EFF_MASK) | CAN_EFF_FLAG
    if msg.is_remote_frame:
        can_id |= CAN_RTR_FLAG
    if msg.is_error_frame:
        can_id |= CAN_ERR_FLAG
    data = bytes(msg.data)
    if msg.is_fd:
        flags = CANFD_FDF | (CANFD_BRS if msg.bitrate_switch else 0) | \
            (CANFD_ESI if msg.error_state_indicator else 0)
        length = next(n for n in _FD_LENGTHS if n >= len(data))   # padded to a valid size
        return _HEAD.pack(can_id, length, flags, 0, 0) + data.ljust(64, b"\0")
    dlc = msg.dlc if msg.is_remote_frame else len(data)
    return _HEAD.pack(can_id, dlc, 0, 0, 0) + data.ljust(8, b"\0")


def decode_frame(frame: bytes | bytearray | memoryview, timestamp: float = 0.0,
                 channel: Any = None) -> can.Message:
    """The ``can.Message`` of one SocketCAN frame (16 or 72 bytes); ValueError if it is
    neither."""
    size = len(frame)
    if size == CAN_MTU:
        can_id, length, data = _CLASSIC.unpack_from(frame)
        if can_id <= CAN_SFF_MASK:      # the common case: a standard data frame
            return can.Message(timestamp=timestamp, arbitration_id=can_id,
                               is_extended_id=False, data=data[:length] if length < 8 else data,
                               channel=channel, is_rx=True, check=False)
    elif size != CANFD_MTU:
        raise ValueError(f"frame of {size} bytes: a CAN frame has {CAN_MTU} or {CANFD_MTU}")
    can_id, length, flags, _, _ = _HEAD.unpack_from(frame)
    fd = size == CANFD_MTU
    extended = bool(can_id & CAN_EFF_FLAG)
    remote = bool(can_id & CAN_RTR_FLAG)
    length = min(length, 64 if fd else 8)
    return can.Message(
        timestamp=timestamp, channel=channel,
        arbitration_id=can_id & (CAN_EFF_MASK if extended else CAN_SFF_MASK),
        is_extended_id=extended, is_remote_frame=remote,
        is_error_frame=bool(can_id & CAN_ERR_FLAG), is_fd=fd,
        bitrate_switch=fd and bool(flags & CANFD_BRS),
        error_state_indicator=fd and bool(flags & CANFD_ESI),
        dlc=length, data=None if remote else bytes(frame[8:8 + length]),
        is_rx=True, check=False)


class SocketPairBus(can.BusABC):
    """One end of a :func:`socketpair_wire` as a python-can bus (see the module docs).

    ``sock`` (a connected SOCK_SEQPACKET socket, or ``fileno`` of one) is owned by the
    bus from now on: :meth:`shutdown` closes it.  ``fd`` selects the frame size sent
    (classic 16 bytes or CAN FD 72 bytes); both sizes are received.
    """

    def __init__(self, sock: socket.socket | None = None, *, fileno: int | None = None,
                 fd: bool = False, channel: str | None = None,
                 can_filters: Any = None, **kwargs: Any) -> None:
        if (sock is None) == (fileno is None):
            raise ValueError("give exactly one of sock and fileno")
        if sock is None:
            assert fileno is not None
            sock = socket.socket(fileno=fileno)
        if sock.type != socket.SOCK_SEQPACKET:
            raise ValueError(f"SocketPairBus needs a SOCK_SEQPACKET socket, got {sock.type!r}")
        sock.setblocking(False)
        self.socket = sock
        self.channel = channel or f"socketpair:{sock.fileno()}"
        self.channel_info = f"socket pair {self.channel}"
        self._fd_frames = bool(fd)
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self._buf = bytearray(CANFD_MTU + 1)
        self._view = memoryview(self._buf)
        self._poll = select.poll()
        self._poll.register(sock.fileno(), select.POLLIN)
        self._closed = False
        self.overflows = 0       #: frames lost because the peer's queue was full
        self.received = 0
        self.sent = 0
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    def fileno(self) -> int:
        return self.socket.fileno()

    # ------------------------------------------------------------------ receive
    @property
    def raw_capable(self) -> bool:
        """Whether :meth:`recv_frame_into` reads what ``recv`` would: no software
        receive filters (``rig.bus.raw``)."""
        return self._filters is None

    def recv_frame_into(self, buf: bytearray) -> int:
        """The next pending frame copied into ``buf`` (SocketCAN's layout, at least
        ``CANFD_MTU + 1`` bytes): its size, 16 or 72; 0 when the queue is empty.  Never
        blocks; no filters applied.  A closed peer, a failed read or a datagram of
        another size raises ``can.CanOperationError`` (``rig.bus.raw.RawFrameReader``)."""
        try:
            n = self.socket.recv_into(buf)
        except BlockingIOError:
            return 0
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}",
                                        error_code=exc.errno) from exc
        if n == 0:
            raise can.CanOperationError(f"{self.channel_info}: the peer closed its end",
                                        error_code=errno.ECONNRESET)
        check_frame_size(n, self.channel_info)
        self.received += 1
        return n

    def _read_one(self) -> can.Message | None:
        """One pending frame, or None when the queue is empty (never blocks)."""
        n = self.recv_frame_into(self._buf)
        if n == 0:
            return None
        if n == CAN_MTU:
            can_id, length, data = _CLASSIC.unpack_from(self._buf)
            if can_id <= CAN_SFF_MASK:      # a standard data frame: decode_frame's fast path
                return can.Message(timestamp=time.time(), arbitration_id=can_id,
                                   is_extended_id=False,
                                   data=data[:length] if length < 8 else data,
                                   channel=self.channel, is_rx=True, check=False)
        return decode_frame(self._view[:n], time.time(), self.channel)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame (that passes the filters), waiting up to ``timeout`` seconds
        (None = for ever, 0 = only what is queued)."""
        if timeout == 0.0 and self._filters is None and not self._closed:
            return self._read_one()     # the control loop's path: no generic overhead
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info}: bus is shut down")
        end = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        filtered = self._filters is not None
        while True:
            msg = self._read_one()
            while msg is not None:
                if not filtered or self._matches_filters(msg):
                    return msg, True
                msg = self._read_one()
            if end is None:
                wait_ms = -1
            else:
                remaining = end - time.monotonic()
                if remaining <= 0:
                    return None, True
                wait_ms = max(1, int(remaining * 1000))
            self._poll.poll(wait_ms)      # PEP 475: retried after a signal handler

    # ------------------------------------------------------------------ transmit
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame.  Never blocks: a full peer queue loses the frame (counted in
        :attr:`overflows`, like a SocketCAN receiver overflow); ``timeout`` is accepted
        for the BusABC signature.  A closed peer raises ``can.CanOperationError``."""
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info}: bus is shut down")
        if msg.is_fd and not self._fd_frames:
            raise can.CanOperationError(f"{self.channel_info}: CAN FD frame on a classic bus")
        self.send_frame(encode_frame(msg))

    def send_frame(self, frame: bytes | bytearray) -> None:
        """Send one frame given in SocketCAN's layout (``rig.bus.raw.RawFrameWriter``),
        as :meth:`send` does: never blocks, a full peer queue loses it (counted)."""
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info}: bus is shut down")
        try:
            self.socket.send(frame)
        except BlockingIOError:
            self.overflows += 1
            return
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: send failed: {exc}",
                                        error_code=exc.errno) from exc
        self.sent += 1

    def shutdown(self) -> None:
        if not self._closed:
            self._closed = True
            with contextlib.suppress(KeyError, ValueError, OSError):
                self._poll.unregister(self.socket.fileno())
            self.socket.close()
        super().shutdown()
