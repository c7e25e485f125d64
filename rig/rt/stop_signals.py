"""SIGTERM / SIGINT at any point of ``rig run`` and ``rig demo``: a clean stop, exit 0.

systemd stops the service with SIGTERM, an operator with Ctrl-C (SIGINT); either can come
while the configuration loads, while the bank is designed, while the bus or the recording
opens, or while the loop runs.  :class:`StopSignals` is installed by ``rig.cli`` before
anything else of those commands runs, and stays until they return:

- while the loop runs, a signal only sets :attr:`StopSignals.event`: the loop ends at
  its next tick and the service shuts down as after ``--duration`` (safe valve command,
  shutdown report, recording closed with its summary);
- before the loop the command calls :meth:`StopSignals.check` between its steps, which
  raises :class:`StopRequested`; inside :meth:`StopSignals.interruptible` (a long pure
  computation, the bank design) the signal raises it at once;
- whatever was already set up is closed; a recording that would hold no tick is removed,
  so a stop leaves a complete recording or none.

Signal handlers run in the main thread, between Python bytecodes: a compiled routine
(numba, LAPACK) finishes its call first.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType
from typing import Any

__all__ = ["STOP_SIGNALS", "StopRequested", "StopSignals"]

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class StopRequested(BaseException):
    """A stop signal arrived before the control loop ran (``signal_name``: SIGTERM...).

    A ``BaseException``, as ``KeyboardInterrupt`` is: raised asynchronously inside
    :meth:`StopSignals.interruptible`, it may land in a library's ``except Exception``
    (matplotlib's colormap set-up, imported with python-control by the design, turned
    it into a ``ValueError``), which must not catch it."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(f"stopped by {signal_name}")
        self.signal_name = signal_name


class StopSignals:
    """The stop signals of one command run (see the module docstring)."""

    def __init__(self, event: threading.Event | None = None) -> None:
        self.event = threading.Event() if event is None else event
        self.signal_name = ""           # the first stop signal received
        self._interruptible = 0
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        return self.event.is_set()

    def request(self, reason: str) -> None:
        """Stop as if a signal named ``reason`` had come (tests, an operator)."""
        if not self.signal_name:
            self.signal_name = reason
        self.event.set()

    def install(self) -> StopSignals:
        """Handle SIGTERM and SIGINT from now on (main thread only: elsewhere Python
        cannot install handlers and this logs a warning and changes nothing)."""
        if threading.current_thread() is not threading.main_thread():
            log.warning("not in the main thread: SIGTERM/SIGINT handlers not installed")
            return self
        for sig in STOP_SIGNALS:
            self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def restore(self) -> None:
        """The handlers from before :meth:`install`."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.request(signal.Signals(signum).name)
        if self._interruptible:
            self._interruptible = 0
            raise StopRequested(self.signal_name)

    def check(self) -> None:
        """Raise :class:`StopRequested` if a stop signal has come."""
        if self.event.is_set():
            raise StopRequested(self.signal_name or "stop request")

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """A stop signal raises :class:`StopRequested` inside this block at once.  Only
        around work that holds nothing to clean up (a computation, not I/O)."""
        self.check()
        self._interruptible += 1
        try:
            yield
        finally:
            self._interruptible = max(0, self._interruptible - 1)
