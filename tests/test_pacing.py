"""rig.rt.pacing.Pacer: one pacing rule for the control loop and the emulated rig,
checked on a simulated clock (no real sleeping, no timing assumption)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from rig.rt.pacing import Pacer

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
