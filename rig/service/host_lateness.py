"""Was a latched fault caused by host lateness?  The numbers, and an honest verdict.

On a host that is not real-time, a thread can be stalled for milliseconds: the loop
wakes late (``OVERRUN_STREAK``), or the emulated rig's frames come late and the loop
sees no SensorData for more than ``safety.stale_ticks`` ticks (``SENSOR_STALE``).  When
such a fault latches, :func:`assess` looks at what was measured over the fault's window
-- the loop's own wake-up lateness and skipped deadlines (:meth:`TimingStats.recent_window`,
a preallocated ring), and, where the loop has a peer probe (the emulated rig of ``rig
demo``, :class:`PeerLateness`), how late the rig's own ticks were -- and attributes the
fault to the host only when that lateness reaches the fault's budget:

* SENSOR_STALE: window = the sensor age (ticks), budget = ``stale_ticks`` periods; a
  genuine sensor loss (the rig ticks on time and sends nothing) is not attributed;
* OVERRUN_STREAK: window = the streak, budget = ``safety.overrun_threshold_s`` (the
  fault is lateness by definition);
* RIG_WATCHDOG, when the rig's drive watchdog is known (``watchdog_ns``, the emulated
  rig's): window = the watchdog and the 100 Hz RigStatus that reports it (watchdog
  ticks + 12), budget = the watchdog less one period (a loop that woke that late left
  the drive that long without a command);
* any other code: the numbers are recorded, nothing is attributed.

Runs only when a fault latches (rare): it may allocate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from rig.service.timing import TimingStats
from rig.wire.protocol import FaultCode

__all__ = ["HostLateness", "PeerLateness", "assess"]


class PeerLateness(Protocol):
    """How late the peer (the emulated rig) was: ``(late_ns, peer_tick)``, its worst
    wake-up lateness over its last ``window_ticks`` ticks or the stall it is in now (time
    since its last tick beyond one period), whichever is larger, and its tick number."""

    def __call__(self, now_ns: int, window_ticks: int, /) -> tuple[int, int]: ...


@dataclass(frozen=True)
class HostLateness:
    """The lateness measured around one fault (recorded with the fault; fixed fields,
    one type each: ``rig_checked`` false = no peer probe, rig fields 0 / -1)."""

    attributed: bool        #: the lateness reached the budget: the host caused it
    window_ticks: int       #: ticks looked at, the current one included
    budget_ms: float        #: lateness that explains the fault
    loop_late_ms: float     #: the loop's worst wake-up lateness in the window
    loop_late_tick: int     #: ... at this loop tick
    skipped: int            #: deadlines the loop skipped in the window
    period_ms: float        #: the loop's period
    rig_checked: bool       #: a peer probe answered
    rig_late_ms: float      #: the emulated rig's worst lateness (or ongoing stall)
    rig_late_tick: int      #: ... at this rig tick (-1: not checked)

    def as_dict(self) -> dict[str, object]:
        return {"attributed": self.attributed, "window_ticks": self.window_ticks,
                "budget_ms": self.budget_ms, "loop_late_ms": self.loop_late_ms,
                "loop_late_tick": self.loop_late_tick, "skipped": self.skipped,
                "period_ms": self.period_ms,
                "rig_checked": self.rig_checked, "rig_late_ms": self.rig_late_ms,
                "rig_late_tick": self.rig_late_tick}

    def phrase(self) -> str:
        """``host lateness: ...`` naming what was late, '' when not attributed."""
        if not self.attributed:
            return ""
        parts = []
        if self.loop_late_ms >= self.budget_ms:
            skipped = f", {self.skipped} deadlines skipped" if self.skipped else ""
            parts.append(f"loop woke {self.loop_late_ms:.1f} ms late at tick "
                         f"{self.loop_late_tick}{skipped}")
        elif self.skipped * self.period_ms >= self.budget_ms:
            parts.append(f"loop skipped {self.skipped} deadlines before tick "
                         f"{self.loop_late_tick}")
        if self.rig_checked and self.rig_late_ms >= self.budget_ms:
            parts.append(f"emulated rig's frames {self.rig_late_ms:.1f} ms late (its tick "
                         f"{self.rig_late_tick})")
        return "host lateness: " + "; ".join(parts)


def assess(code: FaultCode, detail: int, tick: int, now_ns: int, timing: TimingStats, *,
           stale_ticks: int, peer: PeerLateness | None = None,
           watchdog_ns: int = 0) -> HostLateness:
    """The lateness around a fault ``code`` (``detail`` = its FaultDetail byte) latched at
    loop ``tick`` (``now_ns`` on the loop's clock); ``watchdog_ns``: the rig's drive
    watchdog (0: unknown); see the module docstring."""
    period = timing.period_ns
    watchdog = code is FaultCode.RIG_WATCHDOG and watchdog_ns > 0
    if code is FaultCode.OVERRUN_STREAK:
        window, budget_ns = max(1, detail), timing.overrun_threshold_ns
    elif watchdog:
        window, budget_ns = -(-watchdog_ns // period) + 12, max(0, watchdog_ns - period)
    else:
        window = max(1, detail if code is FaultCode.SENSOR_STALE else stale_ticks + 1)
        budget_ns = stale_ticks * period
    late_ns, ago, skipped = timing.recent_window(window)
    rig_late_ns, rig_tick, checked = 0, -1, False
    if peer is not None and code is FaultCode.SENSOR_STALE:
        try:
            rig_late_ns, rig_tick = peer(now_ns, window)
            checked = True
        except Exception:   # a probe must never break the fault path
            rig_late_ns, rig_tick = 0, -1
    # a stall shows as a late wake-up, or (between two ticks) as skipped deadlines
    loop_behind_ns = max(late_ns, skipped * period)
    late_enough = loop_behind_ns >= budget_ns or rig_late_ns >= budget_ns
    if code is FaultCode.OVERRUN_STREAK:
        attributed = loop_behind_ns > budget_ns
    elif code is FaultCode.SENSOR_STALE:
        attributed = late_enough
    elif watchdog:
        attributed = loop_behind_ns >= budget_ns
    else:
        attributed = False
    return HostLateness(attributed, window, budget_ns / 1e6, late_ns / 1e6, tick - ago,
                        skipped, period / 1e6, checked, rig_late_ns / 1e6, rig_tick)
