"""The bus abstraction: python-can's :class:`can.BusABC`, opened from ``cfg.can``.

``open_bus(cfg.can, role="controller")`` returns a SocketCAN bus (classic CAN; CAN FD
if ``fd = true``; the bit rate is a property of the kernel interface, set with
``ip link set can0 type can bitrate 1000000``) or python-can's in-process virtual bus
(``receive_own_messages=False``), with receive filters for the frames the role needs.
Every other ``BusABC`` (a replay, a test double) works with the rest of the project.

Helpers here never raise on bus trouble: :func:`safe_send`, :func:`iter_pending` and
:func:`drain_latest` map ``can.CanError`` / ``OSError`` and received error frames to
``FaultCode.BUS_ERROR`` or ``FaultCode.BUS_OFF`` (:func:`classify_bus_exception`,
:func:`classify_error_frame`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import socket
from collections.abc import Collection, Iterator, Sequence
from typing import Any, Final

import can

from controller.config import CanConfig, ConfigError
from rig.wire.protocol import CONTROLLER_RX_IDS, FRAME_LENGTH, RIG_RX_IDS, FaultCode

__all__ = [
    "ROLES",
    "classify_bus_exception",
    "classify_error_frame",
    "drain_latest",
    "errno_of",
    "iter_pending",
    "make_tx_message",
    "open_bus",
    "receive_filters",
    "safe_send",
    "set_receive_buffer",
    "shutdown_all",
]

log = logging.getLogger(__name__)

#: role -> CAN IDs it receives (None = everything, e.g. a logger)
ROLES: Final[dict[str, tuple[int, ...] | None]] = {
    "controller": CONTROLLER_RX_IDS,
    "rig": RIG_RX_IDS,
    "monitor": None,
}

# linux/can/error.h: error class bits in the arbitration ID of an error frame
CAN_ERR_TX_TIMEOUT: Final = 0x001
CAN_ERR_LOSTARB: Final = 0x002
CAN_ERR_CRTL: Final = 0x004
CAN_ERR_PROT: Final = 0x008
CAN_ERR_TRX: Final = 0x010
CAN_ERR_ACK: Final = 0x020
CAN_ERR_BUSOFF: Final = 0x040
CAN_ERR_BUSERROR: Final = 0x080
CAN_ERR_RESTARTED: Final = 0x100
CAN_ERR_CRTL_ACTIVE: Final = 0x40  # data[1]: controller back to error-active
_BUS_OFF_ERRNOS: Final = frozenset({errno.ENETDOWN, errno.ENODEV, errno.ENXIO,
                                    errno.ENETUNREACH})


def receive_filters(role: str | None) -> list[dict[str, Any]] | None:
    """python-can ``can_filters`` for ``role`` (exact 11-bit IDs), None = receive all."""
    if role is None:
        return None
    if role not in ROLES:
        raise ConfigError("role", role, f"one of {sorted(ROLES)}")
    ids = ROLES[role]
    if ids is None:
        return None
    return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids]


def open_bus(can_cfg: CanConfig, *, role: str | None = None, **overrides: Any) -> can.BusABC:
    """Open the bus described by ``can_cfg`` (``interface``, ``channel``, ``fd``).

    ``role`` ("controller", "rig", "monitor" or None) sets the kernel receive filters
    (SocketCAN; the virtual bus gets none, see below);
    ``overrides`` replace config values (``interface=``, ``channel=``, ``fd=``) or are
    passed through to python-can (``can_filters=``, ``rx_queue_size=``...).
    Raises :class:`ConfigError` for an unknown interface and ``can.CanError`` /
    ``OSError`` if the interface cannot be opened (e.g. no such SocketCAN device).
    """
    interface = overrides.pop("interface", can_cfg.interface)
    channel = overrides.pop("channel", can_cfg.channel)
    fd = bool(overrides.pop("fd", can_cfg.fd))
    overrides.pop("bitrate", None)  # a SocketCAN bit rate belongs to the kernel interface
    filters = receive_filters(role)
    overrides.setdefault("receive_own_messages", False)
    if interface == "socketcan":
        overrides.setdefault("can_filters", filters)
        bus = can.Bus(interface="socketcan", channel=channel, fd=fd, **overrides)
        set_receive_buffer(getattr(bus, "socket", None), can_cfg.receive_buffer_bytes)
        return bus
    if interface == "virtual":
        # no role filters here: python-can filters the virtual bus in software, and then
        # recv(timeout=0) returns None at the first non-matching frame although matching
        # ones are queued behind it.  Consumers dispatch by ID (or pass ``ids`` to
        # iter_pending / drain_latest).  Explicit ``can_filters=`` are still honoured.
        return can.Bus(interface="virtual", channel=channel, **overrides)
    raise ConfigError("can.interface", interface, "one of 'socketcan', 'virtual'")


def set_receive_buffer(sock: Any, size_bytes: int) -> int | None:
    """Best effort: ask for a ``size_bytes`` SO_RCVBUF on ``sock`` (a SocketCAN bus's
    ``.socket``) so a late tick does not lose frames; never raises.

    Returns the size the kernel reports afterwards (Linux doubles the request and caps it
    at ``net.core.rmem_max`` for unprivileged processes; SO_RCVBUFFORCE is tried first),
    or None when ``size_bytes`` is 0, there is no socket or it refused (logged)."""
    if size_bytes <= 0 or sock is None:
        return None
    force = getattr(socket, "SO_RCVBUFFORCE", None)
    try:
        if force is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, force, size_bytes)
            except OSError:    # needs CAP_NET_ADMIN: fall back to the capped option
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size_bytes)
        else:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size_bytes)
        got = int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except (OSError, AttributeError, TypeError, ValueError) as exc:
        log.warning("could not set the CAN receive buffer to %d bytes: %s", size_bytes, exc)
        return None
    if got < size_bytes:
        log.warning("CAN receive buffer is %d bytes, %d requested (raise "
                    "net.core.rmem_max or run with CAP_NET_ADMIN)", got, size_bytes)
    else:
        log.info("CAN receive buffer %d bytes", got)
    return got


def make_tx_message(frame_id: int, fd: bool = False) -> can.Message:
    """A reusable 8-byte transmit message: encode into ``msg.data`` in place, then send.

    (python-can's virtual bus copies on send and SocketCAN packs on send, so reusing one
    Message per frame ID is safe.)
    """
    return can.Message(arbitration_id=frame_id, is_extended_id=False,
                       data=bytearray(FRAME_LENGTH), is_fd=fd, check=True)


def errno_of(exc: BaseException) -> int | None:
    """The OS errno behind a python-can / OS exception (or its cause), if any."""
    for e in (exc, exc.__cause__, exc.__context__):
        if e is None:
            continue
        code = getattr(e, "error_code", None) or getattr(e, "errno", None)
        if isinstance(code, int):
            return code
    return None


def classify_bus_exception(exc: BaseException) -> FaultCode:
    """BUS_OFF when the interface is down/gone, else BUS_ERROR (queue full, timeout...)."""
    code = errno_of(exc)
    if code is not None and code in _BUS_OFF_ERRNOS:
        return FaultCode.BUS_OFF
    return FaultCode.BUS_ERROR


def classify_error_frame(msg: can.Message) -> FaultCode:
    """Fault of a received frame: NONE for a data frame or a benign error frame (lost
    arbitration, controller restarted / back to error-active), BUS_OFF for bus-off,
    BUS_ERROR for every other error class."""
    if not msg.is_error_frame:
        return FaultCode.NONE
    cls = msg.arbitration_id
    if cls & CAN_ERR_BUSOFF:
        return FaultCode.BUS_OFF
    serious = cls & (CAN_ERR_TX_TIMEOUT | CAN_ERR_PROT | CAN_ERR_TRX | CAN_ERR_ACK
                     | CAN_ERR_BUSERROR)
    if serious:
        return FaultCode.BUS_ERROR
    if cls & CAN_ERR_CRTL:
        data = msg.data
        if len(data) > 1 and data[1] == CAN_ERR_CRTL_ACTIVE:
            return FaultCode.NONE
        return FaultCode.BUS_ERROR
    return FaultCode.NONE


def safe_send(bus: can.BusABC, msg: can.Message, timeout: float | None = 0.0) -> FaultCode:
    """Send without raising: NONE on success, else the mapped bus fault."""
    try:
        bus.send(msg, timeout)
    except (can.CanError, OSError) as exc:
        return classify_bus_exception(exc)
    return FaultCode.NONE


def iter_pending(bus: can.BusABC, max_frames: int = 4096,
                 faults: list[FaultCode] | None = None,
                 ids: Collection[int] | None = None) -> Iterator[can.Message]:
    """Yield every frame already received (``recv(timeout=0)`` loop), at most
    ``max_frames`` read, only standard-ID frames in ``ids`` if given.  Error frames and
    receive exceptions end up in ``faults`` (if given) as FaultCodes; error frames are
    not yielded.  Never blocks, never raises."""
    for _ in range(max_frames):
        try:
            msg = bus.recv(timeout=0.0)
        except (can.CanError, OSError) as exc:
            if faults is not None:
                faults.append(classify_bus_exception(exc))
            return
        if msg is None:
            return
        if msg.is_error_frame:
            fault = classify_error_frame(msg)
            if fault and faults is not None:
                faults.append(fault)
            continue
        if ids is not None and (msg.is_extended_id or msg.arbitration_id not in ids):
            continue
        yield msg


def drain_latest(bus: can.BusABC, latest: dict[int, can.Message],
                 max_frames: int = 4096,
                 ids: Collection[int] | None = None) -> tuple[int, FaultCode]:
    """Read all pending frames, keeping the latest per arbitration ID in ``latest``
    (only IDs in ``ids`` if given).

    Returns (data frames kept, worst bus fault seen: NONE < BUS_ERROR < BUS_OFF).
    """
    faults: list[FaultCode] = []
    n = 0
    for msg in iter_pending(bus, max_frames, faults, ids):
        latest[msg.arbitration_id] = msg
        n += 1
    return n, max(faults, default=FaultCode.NONE)


def shutdown_all(buses: Sequence[can.BusABC]) -> None:
    """Shut down several buses, ignoring errors (test and CLI clean-up)."""
    for b in buses:
        with contextlib.suppress(can.CanError, OSError):
            b.shutdown()
