"""The controller service against the emulated rig in real time: one harness for
``rig demo``, the loop benchmark (``bench/loop_bench.py``) and the tests.

The service (:class:`rig.service.runner.Service`, its loop in the calling thread) and the
emulated rig (:class:`hil.rig_process.RigProcess`, a process of its own) are connected
by one :mod:`rig.bus.socketpair` wire, as ``rig run`` and ``rig hil`` are by a vcan/can
interface on the bench.  Each side has its own real-time set-up (the service's
``ServiceOptions.realtime``, the rig's ``RigProcessOptions.realtime``); neither shares a
GIL, a garbage collector or a memory lock with the other.

:meth:`RigHarness.run`, in this order:

1. the rig process was started by the constructor and sets itself up while the service
   designs its bank; wait until it is ready;
2. the loop starts; after ``rig_start_ticks`` ticks (the loop settled) the rig's first
   tick is scheduled half a period after a loop deadline, so that its SensorData arrives
   mid-period instead of racing the loop's read.  The rig drops what was sent before it
   started (a node joining a bus sees only the frames that follow), so its drive
   watchdog arms with a fresh ValveCommand;
3. the caller's ``on_tick`` runs after every loop tick (its operator: arm, reset ...);
   a rig process that ends stops the run;
4. the loop ends (``duration_s``, a stop signal, the caller setting
   ``service.stop_event``); as the service enters STOPPING (and sends its safe valve
   command and shutdown report) the rig is asked to stop, so that its drive watchdog does
   not trip while the service closes its recording; the rig reports its counters and
   the true plant signals it traced come back in :attr:`HarnessResult.trace`.

Stopped before the loop ran (a stop signal during the set-up), nothing runs, no
recording is left and :attr:`HarnessResult.ticks_run` is 0.

Lockstep (``RigProcessOptions(lockstep=True)``, :mod:`rig.rt.lockstep`): the same two
processes on the same wire, but they take turns, rig tick k then loop tick k, handed over
on a second socket pair.  The loop's clock is a :class:`rig.rt.pacing.SteppedClock` at
``rig.rt.lockstep.START_NS + k period`` (no lateness, compute time 0) and its pacer a
:class:`rig.rt.lockstep.LockstepPacer` (wall clock best effort, at most ``max_speedup`` x
real time); the rig runs from the loop's tick 0 (no warm-up ticks alone, nothing to
drop) until the service closes the turn channel after its shutdown frames.  The run is
then the one :func:`hil.stepped_run.record_emulated_run` computes in one process, bit for
bit, whatever the host's scheduling.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig
from hil.rig_process import RigProcess, RigProcessError, RigProcessOptions, RigTrace
from rig.bus.socketpair import SocketPairBus, socketpair_wire
from rig.rt.lockstep import START_NS, LockstepLink, LockstepPacer, lockstep_pair
from rig.rt.pacing import SteppedClock

__all__ = ["HarnessResult", "RigHarness", "RigProcessError", "RigProcessOptions"]

log = logging.getLogger(__name__)

#: loop ticks before the rig's first tick
RIG_START_TICKS = 100
#: loop ticks between two checks that the rig process still runs
_ALIVE_EVERY = 100


@dataclass
class HarnessResult:
    """What one :meth:`RigHarness.run` leaves besides the service itself."""

    ticks_run: int = 0                          # loop ticks
    rig_started_at: int = -1                    # loop tick after which the rig started
    rig_stats: dict[str, Any] = field(default_factory=dict)   # hil.node.NodeStats
    rig_realtime: dict[str, Any] = field(default_factory=dict)
    rig_error: str | None = None
    trace: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    #: lockstep only: realtime_factor (loop time / wall time), behind_s (wall time the
    #: pace was re-anchored by after host stalls), stalls
    lockstep: dict[str, float] = field(default_factory=dict)


class RigHarness:
    """The service and the emulated rig process on one wire (see the module docstring).

    ``service_options`` as for :class:`rig.service.runner.Service` (``interface`` / ``channel``
    are ignored: the bus is the wire); ``metadata`` goes into the recording; ``stop``:
    the command's installed :class:`rig.rt.stop_signals.StopSignals`; ``max_speedup``:
    lockstep only, see :class:`rig.rt.lockstep.LockstepPacer`.  Raises what the service's
    constructor raises (after stopping the rig process)."""

    def __init__(self, cfg: RigConfig, service_options: Any,
                 rig_options: RigProcessOptions | None = None, *,
                 metadata: dict[str, Any] | None = None, stop: Any = None,
                 rig_start_ticks: int = RIG_START_TICKS, max_speedup: float = 1.0) -> None:
        from rig.service.runner import Service

        self.cfg = cfg
        self.rig_options = rig_options or RigProcessOptions()
        self.rig_start_ticks = max(1, int(rig_start_ticks))
        self.max_speedup = float(max_speedup)
        ours, theirs = socketpair_wire()
        self.turns: LockstepLink | None = None
        self.clock: SteppedClock | None = None
        rig_turns = None
        if self.rig_options.lockstep:
            loop_turns, rig_turns = lockstep_pair()
            self.turns = LockstepLink(loop_turns)
            self.clock = SteppedClock()
            self.clock.now_ns = START_NS
        self.rig = RigProcess(cfg, self.rig_options, theirs, rig_turns)
        self.bus = SocketPairBus(ours, fd=cfg.can.fd, channel="controller")
        try:
            # the rig's own errors (road, configuration) before the long design
            self.rig.wait_built(stop_event=None if stop is None else stop.event)
            self.service = Service(cfg, service_options, bus=self.bus, metadata=metadata,
                                   stop=stop, clock=self.clock)
        except BaseException:
            if self.turns is not None:
                self.turns.close()
            self.rig.close()
            self.bus.shutdown()
            raise
        self.result = HarnessResult()
        self._period_ns = self.service.loop.period_ns
        # the rig stops once the safe command is on the wire, not before: it must see it
        self.service.after_shutdown_frames.append(self.rig.request_stop)
        if self.turns is not None:      # the rig waits for a turn: this ends its wait
            self.service.after_shutdown_frames.append(self.turns.close)
        elif self.rig_options.trace_ticks > 0:
            # real time: a SENSOR_STALE asks the rig's trace how late its ticks were
            self.service.loop.peer_lateness = functools.partial(
                self.rig.trace.lateness, period_ns=self._period_ns)
        if self.turns is None and self.rig_options.watchdog_s:
            # real time: a RIG_WATCHDOG is weighed against the drive's own watchdog
            self.service.loop.peer_watchdog_ns = round(self.rig_options.watchdog_s * 1e9)

    @property
    def trace(self) -> RigTrace:
        """The rig's live trace (``count``, ``arrays``); read-only here."""
        return self.rig.trace

    def run(self, on_tick: Callable[[Any], None] | None = None) -> HarnessResult:
        """Wait for the rig, run the service's loop, stop both; see the module docstring.
        RigProcessError if the rig process could not be set up."""
        svc = self.service
        res = self.result
        try:
            res.rig_realtime = self.rig.wait_ready(
                stop_event=svc.stop_event).get("realtime", {})
            self._drain()
            pacer = None
            if self.turns is not None and self.clock is not None:
                pacer = LockstepPacer(self._period_ns, self.clock, self.turns,
                                      start_ns=START_NS, stop=svc.stop_event,
                                      max_speedup=self.max_speedup)
                res.rig_started_at = 0      # rig tick 0 comes before loop tick 0

            def hook(loop: Any) -> None:
                tick = loop.tick_count
                if res.rig_started_at < 0:
                    if tick >= self.rig_start_ticks:
                        res.rig_started_at = tick
                        deadline = loop.t_ns - loop.lateness_ns
                        self.rig.start_at(deadline + self._period_ns + self._period_ns // 2)
                elif tick % _ALIVE_EVERY == 0 and not self.rig.alive:
                    res.rig_error = self.rig.error or "the emulated rig process ended"
                    log.error("%s: stopping the run", res.rig_error)
                    svc.exit_reason = svc.exit_reason or "emulated rig process ended"
                    svc.stop_event.set()
                    return
                if on_tick is not None:
                    on_tick(loop)

            svc.run(on_tick=hook, pacer=pacer)
            if pacer is not None:
                res.rig_error = res.rig_error or pacer.error
                res.lockstep = {"realtime_factor": pacer.realtime_factor,
                                "behind_s": pacer.behind_ns * 1e-9,
                                "stalls": float(pacer.stalls)}
        finally:
            svc.close()
            res.ticks_run = svc.ticks_run
            if self.turns is not None:  # (closed already unless the loop never ran)
                self.turns.close()
            res.rig_stats = self.rig.stop()
            res.rig_error = res.rig_error or self.rig.error
            res.trace = self.rig.trace.copy()
            self.bus.shutdown()
        return res

    def _drain(self) -> None:
        """Whatever reached the wire before the loop (nothing, normally) is not news."""
        while self.bus.recv(0.0) is not None:
            pass

    def close(self) -> None:
        """Stop what still runs and unmap the rig's trace (idempotent; after
        :meth:`run`, or instead of it)."""
        self.service.close()
        if self.turns is not None:      # a lockstep rig waits for its turn until then
            self.turns.close()
        self.rig.close()
        self.bus.shutdown()
