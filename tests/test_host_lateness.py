"""Issue 24: a fault caused by host lateness says so (rig/service/host_lateness.py).

A stall of the host (the loop woke late, or the emulated rig's frames came late) that
makes SENSOR_STALE / OVERRUN_STREAK latch is named in the fault's record (the recorded
event's ``host_lateness``, ``status()``, the message); a genuine sensor loss is not."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from controller.config import default_config
from rig.rt.pacing import Pacer
from rig.service.timing import RECENT_TICKS, TimingStats
from rig.wire.protocol import FaultCode, LifecycleState
from tests.support.loop_harness import PERIOD_NS, LoopHarness, make_harness

CFG = default_config()
STALE = CFG.safety.stale_ticks
MS = 1_000_000


def _fault(h: LoopHarness) -> dict[str, Any]:
    lc = h.loop.lifecycle
    assert lc.state is LifecycleState.FAULT
    tr = h.loop.transitions[-1]
    assert tr.state is LifecycleState.FAULT and tr.host_lateness is not None
    assert h.loop.status()["fault_host_lateness"] == tr.host_lateness
    assert tr.as_dict()["host_lateness"] == tr.host_lateness
    return dict(tr.host_lateness)


def test_a_stall_of_the_loop_names_host_lateness(armed: LoopHarness) -> None:
    h = armed
    h.step(sensor=False, lateness_ns=3 * MS)       # the host stalled loop and rig alike
    stall_tick = h.loop.tick_count - 1
    for _ in range(STALE):
        h.step(sensor=False)
    assert h.loop.lifecycle.fault_code is FaultCode.SENSOR_STALE
    cause = _fault(h)
    assert cause["attributed"] is True
    assert cause["loop_late_ms"] == 3.0 and cause["loop_late_tick"] == stall_tick
    assert cause["window_ticks"] == STALE + 1 and cause["budget_ms"] == STALE * 1.0
    assert cause["rig_checked"] is False
    assert (f"host lateness: loop woke 3.0 ms late at tick {stall_tick}"
            in h.loop.lifecycle.fault_message)


def test_a_genuine_sensor_loss_is_not_host_lateness(armed: LoopHarness) -> None:
    h = armed
    h.loop.peer_lateness = lambda now_ns, window: (50_000, 1234)   # the rig ticks on time
    for _ in range(STALE + 1):
        h.step(sensor=False, lateness_ns=40_000)
    assert h.loop.lifecycle.fault_code is FaultCode.SENSOR_STALE
    cause = _fault(h)
    assert cause["attributed"] is False
    assert cause["rig_checked"] is True and cause["rig_late_ms"] == 0.05
    assert "host lateness" not in h.loop.lifecycle.fault_message


def test_late_frames_of_the_emulated_rig_name_host_lateness(armed: LoopHarness) -> None:
    h = armed
    asked: list[tuple[int, int]] = []

    def rig_stalled(now_ns: int, window: int) -> tuple[int, int]:
        asked.append((now_ns, window))
        return 4 * MS, 777                          # the rig is 4 ms into a stall

    h.loop.peer_lateness = rig_stalled
    for _ in range(STALE + 1):
        h.step(sensor=False)
    cause = _fault(h)
    assert asked == [(h.t_ns - PERIOD_NS, STALE + 1)]
    assert cause["attributed"] is True and cause["rig_late_ms"] == 4.0
    assert cause["rig_late_tick"] == 777
    assert "emulated rig's frames 4.0 ms late (its tick 777)" in h.loop.lifecycle.fault_message
    assert "loop woke" not in h.loop.lifecycle.fault_message


def test_a_failing_probe_does_not_stop_the_latch(armed: LoopHarness) -> None:
    h = armed

    def broken(now_ns: int, window: int) -> tuple[int, int]:
        raise RuntimeError("probe")

    h.loop.peer_lateness = broken
    for _ in range(STALE + 1):
        h.step(sensor=False)
    assert h.loop.lifecycle.fault_code is FaultCode.SENSOR_STALE
    assert _fault(h)["rig_checked"] is False


def test_an_overrun_streak_names_the_loop_lateness(armed: LoopHarness) -> None:
    h = armed
    lates = [600_000, 700_000, 2_500_000, 800_000, 900_000]
    for late in lates:
        h.step(lateness_ns=late)
    assert h.loop.lifecycle.fault_code is FaultCode.OVERRUN_STREAK
    cause = _fault(h)
    assert cause["attributed"] is True and cause["loop_late_ms"] == 2.5
    assert cause["loop_late_tick"] == h.loop.tick_count - 3
    assert "host lateness: loop woke 2.5 ms late" in h.loop.lifecycle.fault_message


def test_other_faults_record_the_numbers_but_attribute_nothing(armed: LoopHarness) -> None:
    h = armed
    h.step(lateness_ns=3 * MS, status=True)
    h.rig.rig_status(supply_ok=0)
    h.step(status=False)
    assert h.loop.lifecycle.fault_code is FaultCode.SUPPLY_LOSS
    cause = _fault(h)
    assert cause["attributed"] is False and cause["loop_late_ms"] == 3.0
    assert "host lateness" not in h.loop.lifecycle.fault_message


class _StallingClock:
    """A fake monotonic clock for :class:`Pacer`: ``sleep`` lands on time, except once
    ``stall_ns`` late at ``stall_at`` (the host stalled the loop in its sleep)."""

    def __init__(self, stall_at: int, stall_ns: int) -> None:
        self.now = 0
        self.sleeps = 0
        self.stall_at, self.stall_ns = stall_at, stall_ns

    def __call__(self) -> int:
        return self.now

    def sleep(self, s: float) -> None:
        self.now += round(s * 1e9) + (self.stall_ns if self.sleeps == self.stall_at else 0)
        self.sleeps += 1


@pytest.mark.parametrize(("stall_ms", "attributed"), [(5, True), (0, False)])
def test_paced_run_stall_vs_sensor_loss(stall_ms: int, attributed: bool) -> None:
    """``ControlLoop.run`` on a :class:`Pacer` with an injected clock: the rig sends a
    frame before every tick until tick 40; with a 5 ms stall in the loop's sleep before
    tick 40 (the host held both) the SENSOR_STALE names host lateness, without it (the
    rig just stopped sending) it does not."""
    clock = _StallingClock(stall_at=40, stall_ns=stall_ms * MS)
    h = make_harness(clock_ns=clock, spin_ns=0)
    try:
        h.rig.sensor()
        h.rig.rig_status()
        stop = threading.Event()

        def rig_turn(loop: Any) -> None:
            if loop.tick_count == 20:
                assert loop.request("arm", timeout_s=None).accepted
            if loop.tick_count < 40:
                h.rig.sensor()
                if loop.tick_count % 10 == 0:
                    h.rig.rig_status()
            if loop.lifecycle.state is LifecycleState.FAULT or loop.tick_count > 80:
                stop.set()

        h.loop.run(stop, on_tick=rig_turn,
                   pacer=Pacer(PERIOD_NS, start_ns=PERIOD_NS, clock=clock, sleep=clock.sleep))
        assert h.loop.lifecycle.fault_code is FaultCode.SENSOR_STALE
        cause = _fault(h)
        assert cause["attributed"] is attributed
        assert ("host lateness: loop woke 5.0 ms late at tick 40"
                in h.loop.lifecycle.fault_message) is attributed
    finally:
        h.close()


def test_recent_window_finds_the_stall_and_the_skipped_deadlines() -> None:
    t = TimingStats(PERIOD_NS, 500_000, ring_size=16)
    for k in range(40):
        t.start_tick(4 * MS if k == 35 else 10_000)
        if k == 36:
            t.add_skipped(3)        # skipped after tick 36, before tick 37
        if k < 39:
            t.end_tick(50_000)      # tick 39 is the current one, not ended yet
    assert t.recent_window(3) == (10_000, 0, 0)         # ticks 37-39: the skip is before
    assert t.recent_window(4) == (10_000, 0, 3)         # ticks 36-39
    assert t.recent_window(5) == (4 * MS, 4, 3)         # tick 35 woke 4 ms late
    assert t.recent_window(10 * RECENT_TICKS)[0] == 4 * MS


def test_the_emulated_rigs_trace_reports_its_lateness_and_an_ongoing_stall() -> None:
    import os

    from hil.rig_process import RigTrace

    fd = os.memfd_create("rig-trace-test")
    trace = RigTrace(fd, 100, create=True)
    try:
        assert trace.lateness(0, 3, period_ns=PERIOD_NS) == (0, -1)      # not started
        wake, late = trace.arrays["wake_s"], trace.arrays["wake_late_s"]
        for i in range(50):                     # on time, one 3 ms late wake-up at 40
            late[i] = 3e-3 if i == 40 else 20e-6
            wake[i] = 10.0 + i * 1e-3 + late[i]
        trace.publish(50)
        now = round((10.0 + 49e-3) * 1e9) + 300_000     # 0.3 ms after the last wake-up
        assert trace.lateness(now, 3, period_ns=PERIOD_NS) == (20_000, 45)
        assert trace.lateness(now, 9, period_ns=PERIOD_NS) == (3_000_000, 40)
        # 5 ms since the last tick woke: 4 ms into a stall (the tick it owes: 50)
        stalled = round(wake[49] * 1e9) + 5 * MS
        assert trace.lateness(stalled, 3, period_ns=PERIOD_NS) == (4 * MS, 50)
    finally:
        trace.close()
        os.close(fd)


def test_the_demo_summary_line_says_whether_the_host_was_late() -> None:
    from rig.commands.demo import fault_line

    base = {"attributed": False, "window_ticks": 3, "budget_ms": 2.0, "loop_late_ms": 0.1,
            "loop_late_tick": 10, "skipped": 0, "period_ms": 1.0, "rig_checked": True,
            "rig_late_ms": 0.2, "rig_late_tick": 9}
    lost = {"time_s": 1.5, "code": "SENSOR_STALE", "reason": "fault SENSOR_STALE: x",
            "host_lateness": base}
    assert fault_line(lost) == (
        "fault at 1.500 s: SENSOR_STALE (fault SENSOR_STALE: x) (not host lateness: loop "
        "at most 0.1 ms late, emulated rig at most 0.2 ms late over 3 ticks, budget 2 ms)")
    late = {**lost, "reason": "fault SENSOR_STALE: x (host lateness: loop woke 5.0 ms late "
            "at tick 10)", "host_lateness": {**base, "attributed": True}}
    assert fault_line(late).endswith("(host lateness: loop woke 5.0 ms late at tick 10))")
    assert fault_line({**lost, "code": "SUPPLY_LOSS"}).endswith("(fault SENSOR_STALE: x)")


@pytest.mark.parametrize(("late_ns", "attributed"), [(4_500_000, True), (300_000, False)])
def test_a_rig_watchdog_after_a_late_wake_up_names_host_lateness(
        armed: LoopHarness, late_ns: int, attributed: bool) -> None:
    h = armed
    h.loop.peer_watchdog_ns = 5 * MS           # the emulated drive's watchdog
    h.step(lateness_ns=late_ns)                 # the drive went without a command
    h.run(6)
    h.rig.rig_status(watchdog=1)                # the next RigStatus reports the trip
    h.step(status=False)
    assert h.loop.lifecycle.fault_code is FaultCode.RIG_WATCHDOG
    cause = _fault(h)
    assert cause["attributed"] is attributed and cause["budget_ms"] == 4.0
    assert cause["window_ticks"] == 17
    assert ("host lateness: loop woke 4.5 ms late" in h.loop.lifecycle.fault_message) \
        is attributed
