"""Frames without a ``can.Message``: the control loop's receive and send path on buses
that take SocketCAN's own frame layout.

python-can builds a new ``can.Message`` for every frame received, on every interface:
about 1.2 µs a frame in the loop's thread, and an allocation per frame in a loop that
otherwise allocates nothing.  A bus that can copy the next frame as it lies on the wire
(``struct can_frame``, 16 bytes; ``struct canfd_frame``, 72 bytes; the flags in the CAN
ID's top bits) into a buffer the loop owns offers :class:`RawFrameReader`, and
:func:`raw_frame_reader` finds it:

- :class:`rig.bus.socketpair.SocketPairBus` (the emulated rig's wire), when it has no
  software receive filters (with filters, its ``recv`` applies them: the Message path);
- python-can's ``SocketcanBus`` (the rig): its raw socket read without blocking; the
  kernel has applied its receive filters already (where it refused them, python-can
  filters in software, and the loop takes the Message path).

The choice is made once, when the loop takes the bus: filters set on it later are not
seen.

The send side is the same idea (:class:`RawFrameWriter`, :func:`raw_frame_writer`): the
loop encodes its frame into a preallocated ``struct can_frame`` and hands over its bytes,
where python-can's ``send`` would pack a new one from the Message (and, on SocketCAN,
``select`` the socket first).  A frame that cannot go out without blocking is an error
as it is for ``send(msg, 0.0)``: ``can.CanOperationError``.

Every other bus (python-can's virtual bus, a replay) has neither, and the loop takes
``recv`` and ``send`` as before.  Only the frame's transport changes: what the loop does
with a frame is the same on both paths (``rig.service.hardware.RigIO``).
"""

from __future__ import annotations

import socket
from typing import Protocol

import can

from rig.bus.socketpair import CANFD_MTU, check_frame_size

__all__ = ["FRAME_BUFFER_BYTES", "RawFrameReader", "RawFrameWriter", "SocketcanRawFrames",
           "raw_frame_reader", "raw_frame_writer"]

#: a receive buffer for :meth:`RawFrameReader.recv_frame_into`: a CAN FD frame and one
#: byte more, so that a longer datagram shows as one (and is refused)
FRAME_BUFFER_BYTES = CANFD_MTU + 1


class RawFrameReader(Protocol):
    """A bus's receive side without ``can.Message``."""

    def recv_frame_into(self, buf: bytearray) -> int:
        """Copy the next pending frame into ``buf`` (at least :data:`FRAME_BUFFER_BYTES`
        long) in SocketCAN's layout and return its size, 16 (classic) or 72 (CAN FD);
        0 when no frame is pending.  Never blocks.  A failed read, or a datagram of any
        other size, raises ``can.CanOperationError`` (with the OS errno as
        ``error_code`` where there is one), as ``recv`` would."""
        ...


class RawFrameWriter(Protocol):
    """A bus's send side without ``can.Message``."""

    def send_frame(self, frame: bytearray) -> None:
        """Send one frame given in SocketCAN's layout (16 or 72 bytes, as the bus takes
        them) without blocking.  A frame that cannot be sent raises
        ``can.CanOperationError`` (with the OS errno as ``error_code`` where there is
        one), as ``send(msg, 0.0)`` would."""
        ...


class SocketcanRawFrames:
    """:class:`RawFrameReader` and :class:`RawFrameWriter` on the raw CAN socket of
    python-can's ``SocketcanBus`` (``MSG_DONTWAIT``: the bus's socket itself stays as
    python-can set it up)."""

    def __init__(self, sock: socket.socket, channel: str) -> None:
        self._recv_into = sock.recv_into
        self._send = sock.send
        self._channel = channel

    def send_frame(self, frame: bytearray) -> None:
        try:
            sent = self._send(frame, socket.MSG_DONTWAIT)
        except OSError as exc:          # EAGAIN / ENOBUFS: the transmit queue is full
            raise can.CanOperationError(f"{self._channel}: failed to transmit: {exc}",
                                        error_code=exc.errno) from exc
        if sent != len(frame):
            raise can.CanOperationError(f"{self._channel}: {sent} of {len(frame)} bytes "
                                        "of a frame sent")

    def recv_frame_into(self, buf: bytearray) -> int:
        try:
            n = self._recv_into(buf, 0, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return 0
        except OSError as exc:
            raise can.CanOperationError(f"{self._channel}: receive failed: {exc}",
                                        error_code=exc.errno) from exc
        check_frame_size(n, self._channel)
        return n


def raw_frame_reader(bus: can.BusABC) -> RawFrameReader | None:
    """The :class:`RawFrameReader` of ``bus``, or None when it has none (read it with
    ``recv``)."""
    from rig.bus.socketpair import SocketPairBus

    if isinstance(bus, SocketPairBus):
        return bus if bus.raw_capable else None
    return _socketcan(bus, need_kernel_filters=True)


def raw_frame_writer(bus: can.BusABC) -> RawFrameWriter | None:
    """The :class:`RawFrameWriter` of ``bus`` (classic frames), or None when it has none
    (send with ``send``)."""
    from rig.bus.socketpair import SocketPairBus

    if isinstance(bus, SocketPairBus):
        return bus
    return _socketcan(bus, need_kernel_filters=False)


def _socketcan(bus: can.BusABC, need_kernel_filters: bool) -> SocketcanRawFrames | None:
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:         # pragma: no cover - python-can without its socketcan module
        return None
    sock = getattr(bus, "socket", None)
    # python-can filters in software only where the kernel refused the filters
    kernel_filtered = bus._filters is None or getattr(bus, "_is_filtered", False)
    if (isinstance(bus, SocketcanBus) and isinstance(sock, socket.socket)
            and (kernel_filtered or not need_kernel_filters)):
        return SocketcanRawFrames(sock, bus.channel_info)
    return None
