"""Absolute-deadline pacing, one rule for the control loop and the emulated rig.

Tick k is due at ``t0 + k * period``.  :meth:`Pacer.wait` sleeps until the current
deadline (``time.sleep`` to within ``spin_ns`` of it, then a busy wait: the sleep's own
wake-up latency does not land on the tick); :meth:`Pacer.advance` moves to the next one.
When the clock is already more than ``max_lag_ns`` past the next deadline (a stall: the
machine, the GIL, a debugger), the missed deadlines are skipped in whole periods and
counted, so the schedule stays on its grid and a stall never turns into a burst of
back-to-back ticks.  Lateness (``now - deadline`` after :meth:`wait`) is the caller's to
count.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

__all__ = ["LOOP_SPIN_NS", "Pacer", "SteppedClock", "TickPacer"]

#: the control loop sleeps to this much before a deadline and spins the rest [ns]
LOOP_SPIN_NS = 60_000


class TickPacer(Protocol):
    """What ``ControlLoop.run`` paces its ticks with: :class:`Pacer` (real time) or
    :class:`rig.rt.lockstep.LockstepPacer` (in turns with the emulated rig)."""

    deadline: int           #: the current tick's deadline [ns, the loop's clock]

    def wait(self) -> int:
        """Block until the current tick is due; the wake-up time [ns]."""
        ...

    def advance(self) -> int:
        """Move to the next tick; the number of deadlines skipped."""
        ...


class SteppedClock:
    """A clock [ns] that reads what its owner last set in :attr:`now_ns`: the loop's
    ``clock_ns`` where time is the tick's, not the machine's (a tick-stepped run, replay).
    The loop reads it once at the end of a tick (compute time = clock - tick time), so
    the owner sets it to tick time + the compute time it wants recorded."""

    __slots__ = ("now_ns",)

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        return self.now_ns


class Pacer:
    """``Pacer(period_ns, start_ns=..., spin_ns=0, max_lag_ns=None)``; ``max_lag_ns``
    None = one period (skip as soon as a whole period was missed).  ``clock`` [ns] and
    ``sleep`` [s] are injectable for tests and replay."""

    def __init__(self, period_ns: int, *, start_ns: int | None = None, spin_ns: int = 0,
                 max_lag_ns: int | None = None,
                 clock: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        self.period_ns = int(period_ns)
        self.spin_ns = max(0, int(spin_ns))
        self.max_lag_ns = self.period_ns if max_lag_ns is None else max(0, int(max_lag_ns))
        self.clock = clock
        self.sleep = sleep
        #: the next tick's deadline [ns, ``clock`` time]
        self.deadline = int(clock() if start_ns is None else start_ns)
        #: deadlines skipped in all, and how many times the schedule skipped
        self.skipped = 0
        self.skips = 0

    def wait(self) -> int:
        """Sleep until the current deadline; the wake-up time [ns]."""
        clock = self.clock
        deadline = self.deadline
        remaining = deadline - clock()
        if remaining > self.spin_ns:
            self.sleep((remaining - self.spin_ns) * 1e-9)
        now = clock()
        while now < deadline:
            now = clock()
        return now

    def advance(self) -> int:
        """Move to the next deadline; the number of deadlines skipped (0 normally)."""
        period = self.period_ns
        self.deadline += period
        behind = self.clock() - self.deadline
        if behind > self.max_lag_ns:
            missed = behind // period
            self.deadline += missed * period
            self.skipped += missed
            self.skips += 1
            return missed
        return 0
