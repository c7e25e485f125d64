"""ControlLoop: deterministic ticking on python-can's virtual bus, frames, pacing, timing.

The harness (``LoopHarness``, ``FakeRuntime``, ``RigSide``) is
tests/support/loop_harness.py, shared with test_safety.py and test_lifecycle.py; the test
at the end runs the real BankRuntime.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from controller.runtime.force_loop import PIForceLoop
from rig.service.timing import TimingStats, histogram_percentile_us
from rig.wire.protocol import (
    FAULT_REPORT,
    VALVE_COMMAND,
    FaultCode,
    FaultReport,
    LifecycleState,
    ValveCommand,
)
from tests.support.loop_harness import PERIOD_NS, LoopHarness, make_harness


@pytest.fixture
def harness() -> Any:
    h = make_harness()
    yield h
    h.close()


# ---------------------------------------------------------------------------- ticking


def test_inactive_sends_safe_command_every_tick_with_counter_echo(harness: LoopHarness) -> None:
    for k in range(20):
        valves, faults = harness.step()
        assert len(valves) == 1 and not faults
        v = valves[0]
        assert v.enable == 0 and v.spool_command == 0.0
        assert v.lifecycle == LifecycleState.INACTIVE
        assert v.counter == k % 16
        assert v.sensor_counter_echo == k % 16
    assert harness.rt.steps == 20  # estimator running warm while INACTIVE


def test_active_command_follows_pi_force_loop(harness: LoopHarness) -> None:
    cfg = harness.loop.cfg
    harness.run(10)
    harness.arm()
    ref_pi = PIForceLoop.from_config(cfg)
    for k in range(30):
        rs = 0.002 * np.sin(0.3 * k)
        valves, _ = harness.step(rattlespace_m=rs, force_n=50.0)
        v = valves[0]
        rs_wire = round(rs / 5e-6) * 5e-6                 # the LVDT as the DBC carries it
        expected = ref_pi.step(-harness.rt.gain * rs_wire, 50.0, rs_wire)
        assert v.enable == 1 and v.lifecycle == LifecycleState.ACTIVE
        assert v.spool_command == pytest.approx(expected, abs=2 / 32767)
        assert v.force_reference_n == pytest.approx(-harness.rt.gain * rs, abs=0.6)


class BrokenRecorder:
    """A recorder whose every hand-off raises (a bug, a closed file ...)."""

    dropped = 0

    def set_tick_layout(self, layout: Any) -> None:
        pass

    def can_frame(self, *args: Any) -> bool:
        raise OSError("recorder gone")

    def tick_packed(self, *args: Any) -> bool:
        raise ValueError("layout mismatch")

    def event(self, *args: Any) -> bool:
        raise OSError("recorder gone")


def test_a_failing_recorder_never_stops_control() -> None:
    """A raising recording hand-off is counted and shown in status(); the valve command
    of every tick still goes out, armed as before, and no fault latches because of it."""
    h = make_harness(recorder=None)
    h.loop.recorder = BrokenRecorder()
    try:
        h.run(10)
        h.arm()
        for _ in range(20):
            valves, faults = h.step(force_n=50.0)
            assert len(valves) == 1 and valves[0].enable == 1 and not faults
        assert h.loop.lifecycle.state is LifecycleState.ACTIVE
        assert h.loop.output_errors >= 3 * 30      # per tick: a frame in, one out, the record
        assert h.loop.status()["last_output_error"] == "ValueError: layout mismatch"
    finally:
        h.close()


class OrderRecorder:
    """A recorder that keeps the items the loop hands it, in their order."""

    dropped = 0

    def __init__(self) -> None:
        self.items: list[tuple[Any, ...]] = []

    def set_tick_layout(self, layout: Any) -> None:
        pass

    def can_frame(self, t_ns: int, tick: int, arbitration_id: int, data: Any, is_rx: bool,
                  error_frame: bool = False, extended_id: bool = False) -> bool:
        self.items.append(("rx" if is_rx else "tx", tick, arbitration_id, bytes(data)))
        return True

    def tick_packed(self, record: Any) -> bool:
        self.items.append(("tick",))
        return True

    def event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool:
        self.items.append(("event", tick, kind))
        return True


def test_frames_reach_the_recording_after_the_valve_command_in_their_order() -> None:
    """The loop hands a tick's frames to the recorder once its frames are out, yet the
    recording gets them in the order they came and went: the frames received before a
    fault, then the fault's event, then the safe command and the fault report with the
    bytes that were sent (the transmit messages are encoded again later), then the
    tick record."""
    rec = OrderRecorder()
    h = make_harness(recorder=rec)
    try:
        h.run(10)
        h.arm()
        start = len(rec.items)

        def broken_step(*_args: Any) -> float:
            raise RuntimeError("bank bug")

        h.rt.step = broken_step          # type: ignore[method-assign]
        tick = h.loop.tick_count
        valves, faults = h.step()
        items = rec.items[start:]
        kinds = [item[0] for item in items]
        assert kinds[0] == "rx" and kinds[-1] == "tick"
        first_event = kinds.index("event")
        assert set(kinds[:first_event]) == {"rx"}
        assert items[first_event][1:] == (tick, "fault")
        tx = [item for item in items if item[0] == "tx"]
        assert tx and kinds.index("tx") > first_event and "rx" not in kinds[first_event:]
        sent_valves = [item[3] for item in tx if item[2] == VALVE_COMMAND.frame_id]
        sent_faults = [item[3] for item in tx if item[2] == FAULT_REPORT.frame_id]
        assert len(sent_valves) == len(valves) == 1 and len(sent_faults) == len(faults) >= 1
        valve = ValveCommand()
        assert VALVE_COMMAND.decode(sent_valves[0], valve).name == "OK"
        assert (valve.enable, valve.spool_command) == (0, 0.0) == (valves[0].enable,
                                                                   valves[0].spool_command)
        for blob, fault in zip(sent_faults, faults, strict=True):
            report = FaultReport()
            assert FAULT_REPORT.decode(blob, report).name == "OK"
            assert report.fault_code == fault.fault_code == FaultCode.EXCEPTION
    finally:
        h.close()


def test_disarm_returns_to_safe_state(harness: LoopHarness) -> None:
    harness.run(10)
    harness.arm()
    harness.step(rattlespace_m=0.01)
    assert harness.rig.valve[-1].enable == 1
    assert harness.loop.request("disarm", timeout_s=None).accepted
    valves, _ = harness.step(rattlespace_m=0.01)
    assert valves[0].enable == 0 and valves[0].spool_command == 0.0
    assert harness.loop.lifecycle.state is LifecycleState.INACTIVE


def test_heartbeat_rate_and_contents(harness: LoopHarness) -> None:
    cfg = harness.loop.cfg
    n = 1000
    harness.run(n)
    every = round(cfg.design.sample_rate_hz / cfg.safety.heartbeat_hz)
    assert len(harness.rig.status) == n // every
    s = harness.rig.status[-1]
    assert s.state == LifecycleState.INACTIVE and s.active_fault == FaultCode.NONE
    assert s.weight_set == cfg.design.weight_set


def test_sensor_values_reach_the_bank_and_are_held_when_missing(harness: LoopHarness) -> None:
    harness.step(rattlespace_m=0.0123, force_n=-250.0, accel_mps2=1.5)
    assert harness.rt.inputs == pytest.approx((0.0123, 1.5, -250.0), abs=1e-5)
    harness.step(sensor=False)   # one missing frame (< stale_ticks): held, no fault
    assert harness.rt.inputs == pytest.approx((0.0123, 1.5, -250.0), abs=1e-5)
    assert harness.loop.lifecycle.state is LifecycleState.INACTIVE


def test_pending_command_is_applied_by_the_loop_thread(harness: LoopHarness) -> None:
    harness.run(10)
    result: list[Any] = []
    th = threading.Thread(target=lambda: result.append(harness.loop.request("arm", None, 2.0)))
    th.start()
    while not harness.loop._requests:
        time.sleep(0.001)
    harness.step()
    th.join(2.0)
    assert result and result[0].accepted
    assert harness.rig.valve[-1].enable == 1


def test_unknown_and_bad_commands_are_refused(harness: LoopHarness) -> None:
    assert not harness.loop.request("selfdestruct", timeout_s=None).accepted
    res = harness.loop.request("weight_set", "x", timeout_s=None)
    assert not res.accepted and "weight_set" in res.message
    assert harness.loop.request("blending", 1, timeout_s=None).accepted
    assert harness.rt.blending == 1
    harness.run(10)
    harness.arm()
    assert not harness.loop.request("blending", 0, timeout_s=None).accepted


def test_tick_allocates_nothing_in_steady_state(harness: LoopHarness) -> None:
    """No container allocation per tick (python-can's own Message objects aside)."""
    harness.run(10)
    harness.arm()
    loop, rig = harness.loop, harness.rig
    # the frames are sent beforehand so the loop's tick is all that runs under tracing
    def one() -> None:
        rig.sensor()
        loop.tick(harness.t_ns, 0)
        harness.t_ns += PERIOD_NS
        rig.read()
    for _ in range(50):
        one()
    tracemalloc.start()
    snap0 = tracemalloc.take_snapshot()
    for _ in range(200):
        one()
    snap1 = tracemalloc.take_snapshot()
    tracemalloc.stop()
    stats = snap1.filter_traces([tracemalloc.Filter(True, "*rig/service/loop.py"),
                                 tracemalloc.Filter(True, "*rig/service/safety.py"),
                                 tracemalloc.Filter(True, "*rig/service/timing.py")]).compare_to(
        snap0.filter_traces([tracemalloc.Filter(True, "*rig/service/loop.py"),
                             tracemalloc.Filter(True, "*rig/service/safety.py"),
                             tracemalloc.Filter(True, "*rig/service/timing.py")]), "lineno")
    grown = sum(s.size_diff for s in stats if s.size_diff > 0)
    assert grown < 2048, [str(s) for s in stats[:5]]


# ---------------------------------------------------------------------------- pacing


def test_run_paces_with_absolute_deadlines(harness: LoopHarness) -> None:
    """200 ticks at 1 kHz take 200 periods (no drift: deadlines are absolute)."""
    stop = threading.Event()
    feeder_stop = threading.Event()

    def feed() -> None:
        while not feeder_stop.is_set():
            harness.rig.sensor()
            time.sleep(0.001)

    th = threading.Thread(target=feed, daemon=True)
    th.start()
    t0 = time.monotonic_ns()
    harness.loop.run(stop, max_ticks=200)
    elapsed = time.monotonic_ns() - t0
    feeder_stop.set()
    th.join()
    assert harness.loop.tick_count + harness.loop.timing.skipped >= 200
    # 200 deadlines -> ~200 ms; generous bounds (shared CI machine), no drift term
    assert 0.195e9 <= elapsed < 0.6e9
    assert harness.loop.timing.count == harness.loop.tick_count


def test_run_skips_ahead_when_badly_late(harness: LoopHarness, monkeypatch: Any) -> None:
    loop = harness.loop
    real_tick = loop.tick
    calls = {"n": 0}

    def slow_tick(now_ns: int, lateness_ns: int = 0) -> None:
        calls["n"] += 1
        real_tick(now_ns, lateness_ns)
        if calls["n"] == 5:
            time.sleep(0.0105)            # ~10 periods lost

    monkeypatch.setattr(loop, "tick", slow_tick)
    loop.run(threading.Event(), max_ticks=20)
    assert loop.timing.skipped >= 9


# ---------------------------------------------------------------------------- timing


def test_timing_percentiles_match_numpy() -> None:
    rng = np.random.default_rng(1)
    late = rng.integers(0, 800_000, size=5000)
    steps = rng.integers(10_000, 90_000, size=5000)
    ts = TimingStats(PERIOD_NS, 500_000, ring_size=4096)
    for a, b in zip(late, steps, strict=True):
        ts.add(int(a), int(b))
    s = ts.summary()
    for q, key in ((50, "p50"), (99, "p99"), (99.9, "p99_9")):
        ref = np.percentile(late // 1000, q, method="inverted_cdf")
        assert s[f"lateness_{key}_us"] == pytest.approx(ref, abs=1.0)
    assert s["lateness_max_us"] == late.max() / 1000
    assert s["overruns"] == int((late > 500_000).sum())
    assert ts.lateness_p99_us() == s["lateness_p99_us"]
    recent_late, recent_step = ts.recent()
    np.testing.assert_array_equal(recent_late, late[-4096:])
    np.testing.assert_array_equal(recent_step, steps[-4096:])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-50_000, 12_000_000), min_size=1, max_size=400),
       st.integers(1, 30))
def test_heartbeat_p99_equals_the_full_histogram_percentile(lateness_ns: list[int],
                                                            hist_max_ms: int) -> None:
    """The two-level lookup of the heartbeat's p99 gives the bin the whole histogram
    gives, and numpy's inverted-CDF percentile of the clipped microseconds."""
    ts = TimingStats(PERIOD_NS, 500_000, ring_size=512, hist_max_us=hist_max_ms * 100)
    for x in lateness_ns:
        ts.add(x, 0)
    clipped = np.clip(np.array(lateness_ns) // 1000, 0, ts.hist_max_us)
    assert ts.lateness_p99_us() == histogram_percentile_us(ts.lateness_hist, 99)
    assert ts.lateness_p99_us() == np.percentile(clipped, 99, method="inverted_cdf")


def test_timing_overrun_streak_counts_consecutive_late_ticks() -> None:
    ts = TimingStats(PERIOD_NS, 500_000)
    pattern = [600_000, 700_000, 100, 900_000, 900_000, 900_000]
    streaks = []
    for x in pattern:
        ts.add(x, 0)
        streaks.append(ts.overrun_streak)
    assert streaks == [1, 2, 0, 1, 2, 3]
    assert ts.overruns == 5


def test_histogram_percentile_empty_is_nan() -> None:
    assert np.isnan(histogram_percentile_us(np.zeros(10, dtype=np.int64), 50))


@pytest.mark.timeout(300)
def test_first_ticks_with_sensor_data_load_no_numba_code(tmp_path: Path) -> None:
    """Every numba kernel a tick calls is loaded before the first tick: a first call
    loads from the cache in ~10 ms (compiles for far longer), beyond the drive's 5 ms
    watchdog.  In a fresh process (nothing compiled yet), the loop's first 300 ticks
    with data take numba's compiler lock zero times."""
    script = textwrap.dedent("""
        import json, sys, time
        from numba.core import event
        from controller.artifact import load_design
        from controller.config import default_config
        from hil.node import RigNode
        from hil.sim.roads import make_road
        from rig.service.runner import Service, ServiceOptions
        from rig.bus.socketpair import SocketPairBus, socketpair_wire

        class Count(event.Listener):
            n = 0
            def on_start(self, ev): Count.n += 1
            def on_end(self, ev): pass

        cfg = default_config()
        a, b = socketpair_wire()
        node = RigNode(SocketPairBus(a), cfg,
                       make_road("rough-course", 11.176, 2.0, cfg.sample_time_s),
                       record_ticks=1)
        for _ in range(3):
            node.tick()                     # the rig's own first calls
        svc = Service(cfg, ServiceOptions(design_path=sys.argv[1], realtime=None,
                                          recording=False, telemetry=False,
                                          install_signal_handlers=False),
                      bus=SocketPairBus(b))
        loop = svc.loop
        t = time.monotonic_ns()
        with event.install_listener("numba:compiler_lock", Count()):
            for k in range(300):
                node.tick()
                loop.tick(t)
                t += 1_000_000
                if k == 100:
                    loop.request("arm", timeout_s=None)
        print(json.dumps({"locks": Count.n, "state": loop.lifecycle.state.name,
                          "rx": loop.rx_frames}))
        svc.close()
    """)
    from controller.artifact import save_design
    from hil.sim.closed_loop import cached_design

    design = tmp_path / "design.npz"
    save_design(cached_design(default_config()), design)
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", script, str(design)], cwd=root,
                         capture_output=True, text=True, timeout=280,
                         env={**os.environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["rx"] > 300 and got["state"] == "ACTIVE"
    assert got["locks"] == 0, got
