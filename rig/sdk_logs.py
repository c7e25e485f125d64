"""What a client of the live view can make the foxglove SDK log, made harmless.

The SDK (Rust) forwards its log records to Python ``logging`` (pyo3-log) under logger
names that are its Rust targets with ``.`` for ``::`` (:data:`SDK_LOGGERS`), and several
of them quote what a client sent: ``Invalid message from 127.0.0.1:40000: unknown
variant `<the op the client chose>` ...``, one record per message, one per unknown
channel of a subscribe.  Unchecked, a client sending ``{`` in a loop writes one ERROR line
per message into the service's log from the SDK's threads (hundreds of thousands, the
loop overrunning), an op name with newlines forges log lines and a 100 KB op name makes
a 100 KB line.

Two defences (docs/foxglove.md):

1. :func:`keep_sdk_logs_out` asks the SDK to forward nothing (its level set to
   CRITICAL, at which it never logs), so no SDK record reaches Python at all; it must
   run before the first server starts (the SDK takes only the first setting).  The
   SDK's own ``FOXGLOVE_LOG_LEVEL`` environment variable overrides it (for debugging the
   SDK); set but empty it is removed (the SDK would take it as set).
2. :class:`ClientTextFilter`, installed on every SDK logger by :func:`install_filter`,
   guards whatever is forwarded all the same: control characters escaped and the text
   capped (:func:`rig.terminal.safe`, :data:`MAX_CHARS`), at most :data:`BURST` records
   per client and kind of record in each :data:`WINDOW_S` window (and
   :data:`GLOBAL_BURST` in all), the rest counted and summarised in one record
   (``foxglove SDK: 5000 more 'Invalid message from 127.0.0.1:40000' records from client
   127.0.0.1:40000 in 1.0 s, not logged``).
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections.abc import Callable
from typing import Final

from rig.terminal import safe

__all__ = ["BURST", "GLOBAL_BURST", "MAX_CHARS", "SDK_LEVEL_ENV", "SDK_LOGGERS", "WINDOW_S",
           "ClientTextFilter", "install_filter", "keep_sdk_logs_out"]

#: the SDK's logger names (its Rust log targets, ``grep -a`` of the extension module of
#: foxglove-sdk 0.30; tests/test_foxglove_logs.py checks that every record a real client
#: provokes comes through a filtered logger)
SDK_LOGGERS: Final = (
    "foxglove.channel.raw_channel", "foxglove.context", "foxglove.log_sink_set",
    "foxglove.mcap_writer", "foxglove.runtime", "foxglove.websocket.advertise",
    "foxglove.websocket.connected_client", "foxglove.websocket.connected_client.poller",
    "foxglove.websocket.connected_client.send_lossy", "foxglove.websocket.server",
    "foxglove.websocket_server", "foxglove_py.websocket", "tungstenite.handshake.server",
    "tungstenite.handshake.machine", "tungstenite.protocol", "tungstenite.protocol.frame",
    "tungstenite.protocol.frame.frame", "tokio_tungstenite.compat",
    "tokio_tungstenite.handshake",
)
#: the SDK's own environment variable that overrides :func:`keep_sdk_logs_out`
SDK_LEVEL_ENV: Final = "FOXGLOVE_LOG_LEVEL"
#: longest SDK log text passed on (escaped), characters
MAX_CHARS: Final = 300
#: rate-limit window, seconds
WINDOW_S: Final = 1.0
#: records passed per (client, kind) in one window
BURST: Final = 3
#: records passed in one window over all clients and kinds
GLOBAL_BURST: Final = 30
#: (client, kind) pairs remembered; more in one window are counted under one key
MAX_KEYS: Final = 256

_CLIENT = re.compile(r"\d{1,3}(?:\.\d{1,3}){3}:\d{1,5}|\[[0-9A-Fa-f:.]+\]:\d{1,5}")
_OVERFLOW = ("-", "(more kinds)")


def _client_and_kind(text: str) -> tuple[str, str]:
    """``Invalid message from 1.2.3.4:5: <detail>`` -> ("1.2.3.4:5", "Invalid message
    from CLIENT"): the client's address and the record's text up to the first ``:``
    after it (the part the SDK wrote, not the client), digits dropped, at most 60."""
    m = _CLIENT.search(text)
    client = m.group() if m else "-"
    rest = text if m is None else text[:m.start()] + "CLIENT" + text[m.end():]
    cut = rest.find(":", rest.find("CLIENT") + 6 if m else 0)
    kind = re.sub(r"\d+", "N", (rest if cut < 0 else rest[:cut])[:120])[:60]
    return client, kind


class ClientTextFilter(logging.Filter):
    """Escapes, caps and rate-limits the records of the SDK's loggers (module docstring).
    ``clock``: seconds, monotonic (tests pass their own)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self._clock = clock
        self._lock = threading.Lock()
        self._window_start = clock()
        self._passed = 0                              # in this window, all keys
        self._counts: dict[tuple[str, str], int] = {}  # records seen per key
        self.suppressed_total = 0

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        client, kind = _client_and_kind(text)
        with self._lock:
            summary = self._roll()
            key = (client, kind)
            if key not in self._counts and len(self._counts) >= MAX_KEYS:
                key = _OVERFLOW
            n = self._counts.get(key, 0) + 1
            self._counts[key] = n
            passes = n <= BURST and self._passed < GLOBAL_BURST
            if passes:
                self._passed += 1
            else:
                self.suppressed_total += 1
        record.msg = safe(text, MAX_CHARS)
        record.args = None
        record.rig_sanitised = True
        if summary:
            record.msg = f"{record.msg} [{summary}]"
        return passes or bool(summary)

    def _roll(self) -> str:
        """Start a new window when the current one is over; the summary of what the
        closed window did not pass ("" when it passed everything)."""
        now = self._clock()
        if now - self._window_start < WINDOW_S:
            return ""
        summary = self._summary(now - self._window_start)
        self._window_start = now
        self._passed = 0
        self._counts = {}
        return summary

    def _summary(self, seconds: float) -> str:
        parts = [f"{n - BURST} more {safe(kind, 80)!r} records from client {safe(client, 80)}"
                 for (client, kind), n in self._counts.items() if n > BURST]
        held = sum(min(n, BURST) for n in self._counts.values()) - self._passed
        if held > 0:
            parts.append(f"{held} more records over the limit of {GLOBAL_BURST} per window")
        if not parts:
            return ""
        more = f" (and {len(parts) - 5} more clients / kinds)" if len(parts) > 5 else ""
        return (f"foxglove SDK: {'; '.join(parts[:5])}{more} in {seconds:.1f} s, "
                "not logged")

    def flush(self, logger: logging.Logger) -> None:
        """Log the summary of the current window now (at close), if it held any back."""
        with self._lock:
            summary = self._summary(self._clock() - self._window_start)
            self._window_start = self._clock()
            self._passed = 0
            self._counts = {}
        if summary:
            logger.warning("%s", summary)


_installed: ClientTextFilter | None = None
_sdk_level_set = False
_guard = threading.Lock()


def install_filter() -> ClientTextFilter:
    """Install one :class:`ClientTextFilter` on every logger of :data:`SDK_LOGGERS`
    (idempotent: returns the one installed)."""
    global _installed
    with _guard:
        if _installed is None:
            _installed = ClientTextFilter()
            for name in SDK_LOGGERS:
                logging.getLogger(name).addFilter(_installed)
        return _installed


def keep_sdk_logs_out() -> None:
    """Ask the SDK to forward no log record to Python (idempotent; before the first
    server starts).  The SDK's call configures the root logger when it has no handler
    (``logging.basicConfig``): that is undone, the service's logging stays as it was."""
    global _sdk_level_set
    import foxglove

    with _guard:
        if _sdk_level_set:
            return
        _sdk_level_set = True
        if os.environ.get(SDK_LEVEL_ENV) == "":
            del os.environ[SDK_LEVEL_ENV]   # the SDK takes "" as set (and forwards)
        root = logging.getLogger()
        handlers, level = list(root.handlers), root.level
        try:
            foxglove.set_log_level(logging.CRITICAL)
        finally:
            for h in root.handlers[:]:
                if h not in handlers:
                    root.removeHandler(h)
            root.setLevel(level)
