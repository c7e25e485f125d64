"""rig.rt.pacing.Pacer: one pacing rule for the control loop and the emulated rig,
checked on a simulated clock (no real sleeping, no timing assumption); and the lockstep
pacer (rig.rt.lockstep), its turns handed over to a rig played by a thread."""

from __future__ import annotations

import itertools
import threading
import tracemalloc

from hypothesis import given
from hypothesis import strategies as st

from rig.rt.lockstep import LockstepLink, LockstepPacer, lockstep_pair
from rig.rt.pacing import Pacer, SteppedClock

PERIOD = 1_000_000


class FakeClock:
    """A clock that sleeping advances, and every reading by 1 us (a busy wait ends)."""

    def __init__(self) -> None:
        self.t = 0

    def __call__(self) -> int:
        self.t += 1_000
        return self.t

    def sleep(self, s: float) -> None:
        self.t += round(s * 1e9)


def test_ticks_land_on_absolute_deadlines() -> None:
    clock = FakeClock()
    pacer = Pacer(PERIOD, start_ns=PERIOD, spin_ns=50_000, clock=clock, sleep=clock.sleep)
    wakes = []
    for _ in range(5):
        wakes.append(pacer.wait())
        clock.t += 300_000                       # the tick's work
        assert pacer.advance() == 0
    assert all(0 <= w - PERIOD * k < 5_000 for k, w in enumerate(wakes, start=1))


def test_a_stall_skips_whole_periods_and_stays_on_the_grid() -> None:
    clock = FakeClock()
    pacer = Pacer(PERIOD, start_ns=PERIOD, clock=clock, sleep=clock.sleep)
    pacer.wait()
    clock.t += 10 * PERIOD + 300_000              # a 10 ms stall in the tick
    missed = pacer.advance()
    assert missed == 9 and pacer.skipped == 9 and pacer.skips == 1
    assert pacer.deadline % PERIOD == 0           # still on the grid
    now = pacer.wait()
    assert 0 <= now - pacer.deadline < PERIOD     # the next tick is due now, not a burst


@given(st.integers(0, 20 * PERIOD), st.integers(0, 5 * PERIOD))
def test_never_more_than_max_lag_behind_after_advance(work: int, max_lag: int) -> None:
    clock = FakeClock()
    pacer = Pacer(PERIOD, start_ns=0, max_lag_ns=max_lag, clock=clock, sleep=clock.sleep)
    pacer.wait()
    clock.t += work
    pacer.advance()
    assert clock.t - pacer.deadline <= max(max_lag, PERIOD)
    assert pacer.deadline % PERIOD == 0


# ---------------------------------------------------------------------------- lockstep


def _peer(link: LockstepLink, log: list[int] | None, ticks: int) -> None:
    """The rig's side: run each turn handed over (noted in ``log``), report it done,
    then close."""
    for _ in range(ticks):
        k = link.wait_go()
        if k is None:
            return
        if log is not None:
            log.append(k)
        link.done(k)
    link.close()


def test_lockstep_pacer_hands_over_turns_on_a_stepped_clock() -> None:
    ours, theirs = lockstep_pair()
    peer_log: list[int] = []
    peer = threading.Thread(target=_peer, args=(LockstepLink(theirs), peer_log, 5))
    peer.start()
    clock = SteppedClock()
    wall = FakeClock()
    stop = threading.Event()
    pacer = LockstepPacer(PERIOD, clock, LockstepLink(ours, timeout_s=5.0),
                          start_ns=10 * PERIOD, stop=stop, wall_ns=wall, sleep=wall.sleep)
    times = []
    for k in range(5):
        now = pacer.wait()
        assert peer_log == list(range(k + 1))        # the rig's tick k came first
        assert now == pacer.deadline == clock() == (10 + k) * PERIOD   # zero lateness
        times.append(wall.t)
        assert pacer.advance() == 0 and clock() == (11 + k) * PERIOD
    # never faster than real time: one period of wall time per tick (the fake wall clock
    # advances 1 us per reading, so a tick may end a few us after its wall time)
    assert all(PERIOD <= b - a < PERIOD + 10_000 for a, b in itertools.pairwise(times))
    assert 0.98 < pacer.realtime_factor <= 1.0 and pacer.error is None and not stop.is_set()
    # the rig closed after 5 ticks: the loop's next turn ends the run instead of hanging
    pacer.wait()
    assert stop.is_set() and pacer.error is not None and pacer.skipped == 0
    peer.join(5.0)


def test_lockstep_pacer_as_fast_as_possible_and_after_a_stall() -> None:
    ours, theirs = lockstep_pair()
    peer = threading.Thread(target=_peer, args=(LockstepLink(theirs), None, 4))
    peer.start()
    wall = FakeClock()
    slept: list[float] = []
    fast = LockstepPacer(PERIOD, SteppedClock(), LockstepLink(ours, timeout_s=5.0),
                         start_ns=0, stop=threading.Event(), max_speedup=0.0,
                         wall_ns=wall, sleep=slept.append)
    for _ in range(2):
        fast.wait()
        fast.advance()
    assert slept == []                      # 0: no pacing at all
    wall.t += 50 * PERIOD                   # the host stalls the loop 50 ms
    fast.wall_period_ns = PERIOD            # ... now paced in real time again
    fast.wait()
    assert fast.stalls == 1 and fast.behind_ns > 40 * PERIOD   # re-anchored, no burst
    fast.advance()
    fast.wait()
    assert slept and 0.0009 < slept[-1] <= 0.001
    peer.join(5.0)


def test_lockstep_turns_allocate_nothing() -> None:
    """A turn of the loop's side reuses its buffers: memory does not grow with ticks."""
    ours, theirs = lockstep_pair()
    peer = threading.Thread(target=_peer, args=(LockstepLink(theirs), None, 600))
    peer.start()
    pacer = LockstepPacer(PERIOD, SteppedClock(), LockstepLink(ours, timeout_s=5.0),
                          start_ns=PERIOD, stop=threading.Event(), max_speedup=0.0)

    def turns(n: int) -> None:
        for _ in range(n):
            pacer.wait()
            pacer.advance()
    turns(100)
    only = [tracemalloc.Filter(True, "*rig/rt/lockstep.py")]
    tracemalloc.start()
    snap0 = tracemalloc.take_snapshot().filter_traces(only)
    turns(400)
    snap1 = tracemalloc.take_snapshot().filter_traces(only)
    tracemalloc.stop()
    grown = sum(s.size_diff for s in snap1.compare_to(snap0, "lineno") if s.size_diff > 0)
    assert grown < 512 and pacer.error is None, snap1.compare_to(snap0, "lineno")[:5]
    peer.join(5.0)
