"""Lockstep timing: a control loop and an emulated rig in two processes take turns tick by
tick, on a loop clock that is the tick count, not the machine's.

Real time on an ordinary computer is best effort: the host stalls a thread for
milliseconds now and then, and a 1 kHz loop reads such a stall as missing sensor data
(SENSOR_STALE) and the rig as missing valve commands (its drive watchdog).  In lockstep
neither side can fall behind the other: the rig's tick k runs, then the loop's tick k,
then the rig's tick k + 1 ... while their CAN frames still travel over their own wire
(the same frames as in real time).  Every safety check counts ticks, so each one works
unchanged; only the wall clock is out of the loop, and it paces the run best effort
(:class:`LockstepPacer`: never faster than ``max_speedup`` x real time).

The turns are handed over on a second socket pair next to the CAN wire, one datagram
(the tick number, int64) per turn (:class:`LockstepLink`):

* loop -> rig ``go k``: run rig tick k (the loop's frames of tick k - 1 are on the wire);
* rig -> loop ``done k``: rig tick k is done (its frames are on the wire).

A frame written to an AF_UNIX socket is in the peer's receive queue when ``send``
returns, so a turn handed over after the frames guarantees that the other side drains
exactly the frames of the tick before; the order of the two queues never races.  The
CAN wire cannot carry the turns itself: which frames make up a tick differs (RigStatus
every tenth tick, heartbeats, FaultReports, frames dropped by fault injection), and a
marker frame would be a frame the DBC does not have.

The loop side uses :class:`LockstepPacer` in place of :class:`rig.rt.pacing.Pacer` with
a :class:`rig.rt.pacing.SteppedClock` as the loop's clock: tick k is at
``start_ns + k period`` exactly, zero lateness; the loop's compute time reads 0 (the
clock does not move inside a tick).  The rig side calls :meth:`LockstepLink.wait_go`
before and :meth:`LockstepLink.done` after each tick.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable

from rig.rt.pacing import SteppedClock

__all__ = ["DEFAULT_TURN_TIMEOUT_S", "START_NS", "LockstepLink", "LockstepPacer",
           "lockstep_pair"]

log = logging.getLogger(__name__)

#: the loop clock's time of tick 0 in lockstep [ns] (as in hil.stepped_run)
START_NS = 1_000_000_000
#: how long one side waits for the other's turn before it gives up [s] (the other side
#: is stuck: a live peer takes well under a millisecond; a dead one ends the wait at once)
DEFAULT_TURN_TIMEOUT_S = 30.0
#: falling more than this behind the wall-clock schedule re-anchors it [ns] (a stalled
#: host is not made up for by a burst faster than the pace asked for)
MAX_BEHIND_NS = 20_000_000


def lockstep_pair() -> tuple[socket.socket, socket.socket]:
    """The two ends of a turn channel: (loop's end, rig's end)."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    return a, b


class LockstepLink:
    """One end of the turn channel (see the module docstring).  Preallocated buffers: a
    turn allocates nothing but the tick number read back.  ``sock`` (or ``fileno``, an
    inherited descriptor) is owned from here on.  A peer that closed its end (or died),
    a turn out of sequence or a wait beyond ``timeout_s`` (None: no limit) ends the link:
    :meth:`wait_go` / :meth:`wait_done` return False and :attr:`error` says why."""

    def __init__(self, sock: socket.socket | None = None, *, fileno: int | None = None,
                 timeout_s: float | None = DEFAULT_TURN_TIMEOUT_S) -> None:
        if sock is None:
            if fileno is None:
                raise ValueError("LockstepLink needs a socket or a file descriptor")
            sock = socket.socket(fileno=fileno)
        self.sock = sock
        sock.settimeout(timeout_s)
        self._out = bytearray(8)
        self._out_view = memoryview(self._out).cast("q")
        self._in = bytearray(8)
        self._in_view = memoryview(self._in).cast("q")
        self.error: str | None = None

    def _send(self, tick: int) -> bool:
        self._out_view[0] = tick
        try:
            self.sock.send(self._out)
        except OSError as exc:
            self.error = self.error or f"lockstep peer gone ({exc})"
            return False
        return True

    def _recv(self, expected: int | None) -> int | None:
        try:
            n = self.sock.recv_into(self._in)
        except TimeoutError:
            self.error = self.error or (f"lockstep peer silent for "
                                        f"{self.sock.gettimeout():g} s")
            return None
        except OSError as exc:
            self.error = self.error or f"lockstep peer gone ({exc})"
            return None
        if n != 8:
            self.error = self.error or "lockstep peer closed the link"
            return None
        tick = int(self._in_view[0])
        if expected is not None and tick != expected:
            self.error = f"lockstep out of step: expected turn {expected}, got {tick}"
            return None
        return tick

    # loop side
    def go(self, tick: int) -> bool:
        """Let the peer run its tick ``tick``."""
        return self._send(tick)

    def wait_done(self, tick: int) -> bool:
        """Wait until the peer reports its tick ``tick`` done."""
        return self._recv(tick) is not None

    # rig side
    def wait_go(self) -> int | None:
        """Wait for the next turn; the tick to run, None when the link ended."""
        return self._recv(None)

    def done(self, tick: int) -> bool:
        """Report tick ``tick`` done (its frames are on the wire)."""
        return self._send(tick)

    def close(self) -> None:
        """End the link (the peer's wait returns at once); idempotent."""
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


class LockstepPacer:
    """The loop side's pacing in lockstep, with :class:`rig.rt.pacing.Pacer`'s interface
    (``deadline``, :meth:`wait`, :meth:`advance`) for ``ControlLoop.run``.

    :meth:`wait` hands the turn to the rig (``go k``), waits for its ``done k``, then
    sleeps, best effort, until tick k's wall time ``t0 + k period / max_speedup``
    (``max_speedup`` 0 or less: no sleeping, as fast as the two processes go); falling
    more than :data:`MAX_BEHIND_NS` behind re-anchors the wall schedule (counted in
    :attr:`behind_ns`) instead of bursting.  It sets ``clock`` to the deadline, which it
    returns: zero lateness.  :meth:`advance` moves the deadline (and ``clock``) one
    period on; it never skips.  When the link ends (the rig process is gone or stuck)
    :attr:`error` is set, ``stop`` is set and the loop's tick runs without the rig."""

    def __init__(self, period_ns: int, clock: SteppedClock, link: LockstepLink, *,
                 start_ns: int, stop: threading.Event, max_speedup: float = 1.0,
                 wall_ns: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        self.period_ns = int(period_ns)
        self.clock = clock
        self.link = link
        self.stop = stop
        self.deadline = int(start_ns)
        clock.now_ns = self.deadline
        #: wall-clock period [ns] (0: as fast as possible)
        self.wall_period_ns = round(self.period_ns / max_speedup) if max_speedup > 0 else 0
        self.wall_ns = wall_ns
        self.sleep = sleep
        self.tick = 0
        self._wall_next = 0
        #: wall time the schedule was re-anchored by, in all [ns]; the count of re-anchors
        self.behind_ns = 0
        self.stalls = 0
        #: Pacer's counters (a lockstep run never skips a tick)
        self.skipped = 0
        self.skips = 0
        #: the wall time the first turn was handed over and the last one came back [ns]
        self.wall_start_ns = 0
        self.wall_end_ns = 0
        self._last_waited = 0
        self.error: str | None = None

    def wait(self) -> int:
        """Hand tick k to the rig, wait for it, pace; the tick's (virtual) time [ns]."""
        k = self.tick
        link = self.link
        if self.error is None and not (link.go(k) and link.wait_done(k)):
            self.error = link.error
            log.error("lockstep: %s; stopping the run", self.error)
            self.stop.set()
        wall = self.wall_ns()
        if k == 0:
            self.wall_start_ns = wall
            self._wall_next = wall
        elif self.wall_period_ns:
            behind = wall - self._wall_next
            if behind < 0:
                self.sleep(-behind * 1e-9)
                wall = self.wall_ns()
            elif behind > MAX_BEHIND_NS:
                self._wall_next += behind
                self.behind_ns += behind
                self.stalls += 1
        self.wall_end_ns = wall
        self._last_waited = k
        self.clock.now_ns = self.deadline
        return self.deadline

    def advance(self) -> int:
        """The next tick: deadline and clock one period on; 0 (nothing is skipped)."""
        self.tick += 1
        self.deadline += self.period_ns
        self._wall_next += self.wall_period_ns
        self.clock.now_ns = self.deadline
        return 0

    @property
    def realtime_factor(self) -> float:
        """Loop time over wall time, first to last tick so far (NaN before two ticks)."""
        wall = self.wall_end_ns - self.wall_start_ns
        return self._last_waited * self.period_ns / wall if wall > 0 else float("nan")
