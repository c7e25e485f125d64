"""systemd notify protocol (``sd_notify(3)``) over a plain AF_UNIX datagram socket.

No dependency on libsystemd.  Outside systemd (``NOTIFY_SOCKET`` unset) every call is a
cheap no-op, so the service runs the same way from a shell, a test or a unit.

Usage::

    notifier = SdNotifier.from_environment()
    notifier.ready("running, INACTIVE")          # READY=1 + STATUS=
    notifier.watchdog_period_ns                   # half of WATCHDOG_USEC, or 0
    notifier.watchdog()                           # WATCHDOG=1 (called from the loop)
    notifier.stopping()                           # STOPPING=1
    notifier.set_note("telemetry", "FAILED: ...") # appended to every STATUS= until None

The watchdog datagram is pre-encoded and sent with a non-blocking ``sendto`` so the
control loop can ping it without allocating or blocking.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

__all__ = ["SdNotifier"]

_WATCHDOG_MSG = b"WATCHDOG=1"


def _socket_address(raw: str) -> str | bytes:
    """``NOTIFY_SOCKET`` value -> address for ``sendto`` (``@name`` = abstract namespace)."""
    if raw.startswith("@"):
        return b"\0" + raw[1:].encode()
    return raw


class SdNotifier:
    """Sends notify datagrams to ``NOTIFY_SOCKET``; inert when it is not set."""

    def __init__(self, notify_socket: str | None, watchdog_usec: int = 0,
                 watchdog_pid: int | None = None) -> None:
        self._address: str | bytes | None = None
        self._notes: dict[str, str] = {}   # standing conditions appended to STATUS=
        self._last_status = ""
        self._sock: socket.socket | None = None
        self.errors = 0
        if notify_socket:
            self._address = _socket_address(notify_socket)
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        # WATCHDOG_PID, when set, names the process the watchdog is meant for.
        enabled = watchdog_usec > 0 and (watchdog_pid is None or watchdog_pid == os.getpid())
        #: ping period: half of the watchdog timeout, in ns (0 = no watchdog requested)
        self.watchdog_period_ns = (watchdog_usec * 1000) // 2 if enabled else 0

    @classmethod
    def from_environment(cls, env: Mapping[str, str] | None = None) -> SdNotifier:
        env = os.environ if env is None else env
        usec_text = env.get("WATCHDOG_USEC", "")
        pid_text = env.get("WATCHDOG_PID", "")
        try:
            usec = int(usec_text) if usec_text else 0
        except ValueError:
            usec = 0
        try:
            pid = int(pid_text) if pid_text else None
        except ValueError:
            pid = None
        return cls(env.get("NOTIFY_SOCKET") or None, usec, pid)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: str | bytes) -> bool:
        """Send one datagram (``KEY=value`` lines).  Never raises; False if not sent."""
        if self._sock is None or self._address is None:
            return False
        data = message.encode() if isinstance(message, str) else message
        try:
            self._sock.sendto(data, self._address)
        except OSError:
            self.errors += 1
            return False
        return True

    def _status_text(self, status: str) -> str:
        self._last_status = status
        notes = list(self._notes.items())
        if not notes:
            return status
        return "; ".join([status, *(f"{k} {v}" for k, v in notes)] if status else
                         [f"{k} {v}" for k, v in notes])

    def ready(self, status: str = "") -> bool:
        text = self._status_text(status)
        return self.notify("READY=1" + (f"\nSTATUS={text}" if text else ""))

    def status(self, status: str) -> bool:
        return self.notify(f"STATUS={self._status_text(status)}")

    def stopping(self, status: str = "") -> bool:
        text = self._status_text(status)
        return self.notify("STOPPING=1" + (f"\nSTATUS={text}" if text else ""))

    def set_note(self, key: str, text: str | None) -> bool:
        """A standing condition (e.g. ``telemetry`` -> ``FAILED: ...``) appended to
        every STATUS= from now on (None removes it); the last status is sent again with
        it at once.  Any thread."""
        if text is None:
            if self._notes.pop(key, None) is None:
                return False
        else:
            self._notes[key] = text
        return self.status(self._last_status)

    def watchdog(self) -> bool:
        """``WATCHDOG=1`` with a pre-encoded message (allocation-free, non-blocking)."""
        return self.notify(_WATCHDOG_MSG)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
