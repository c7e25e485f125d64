"""Every fault path: the safe ValveCommand (Enable=0) is on the bus within one tick of the
fault becoming observable, the FaultReport carries the right FaultCode, FAULT latches.

Tick-stepped on python-can's virtual bus, no sleeping.  The controller's side is the
real ControlLoop; the rig's side is ``RigSide`` (hand-made frames) here and the emulated
rig with its FaultSchedule in test_safety_hil below.
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.artifact import Design
from controller.config import default_config
from controller.runtime.force_loop import PIForceLoop
from hil.faults import FaultSchedule
from rig.bus.core import open_bus
from rig.service.loop import ControlLoop
from rig.service.safety import (
    DETAIL_ACCEL,
    DETAIL_ESTIMATOR,
    DETAIL_FORCE,
    DETAIL_OUTPUT,
    DETAIL_RATTLESPACE,
    DETAIL_RIG_STATUS,
    DETAIL_SEND,
    DETAIL_SENSOR_DATA,
    FaultMonitor,
)
from rig.wire.protocol import (
    FaultCode,
    FaultReport,
    LifecycleState,
    ValveCommand,
)
from tests.support.frames import drain_controller_frames
from tests.support.loop_harness import LoopHarness, make_harness

CFG = default_config()


def assert_faulted_now(h: LoopHarness, valves: list[Any], faults: list[Any],
                       code: FaultCode, detail: int | None = None) -> None:
    """The tick just run sent the safe command and a FaultReport with ``code``."""
    assert h.loop.lifecycle.state is LifecycleState.FAULT
    assert h.loop.lifecycle.fault_code is code
    assert valves, "no ValveCommand sent this tick"
    v = valves[-1]
    assert v.enable == 0 and v.spool_command == 0.0 and v.force_reference_n == 0.0
    assert v.lifecycle == LifecycleState.FAULT
    assert faults, "no FaultReport sent this tick"
    f = faults[0]
    assert f.fault_code == code and f.fault_state == LifecycleState.FAULT
    assert f.fault_tick == h.loop.lifecycle.fault_tick == h.loop.tick_count - 1
    if detail is not None:
        assert f.fault_detail == detail


def assert_latched(h: LoopHarness, code: FaultCode, ticks: int = 110) -> None:
    """Stays FAULT with the safe command while healthy frames flow (until reset); the
    heartbeat reports the fault and the FaultReport is repeated with it."""
    n_status = len(h.rig.status)
    n_faults = len(h.rig.faults)
    for _ in range(ticks):
        valves, _ = h.step()
        assert valves[-1].enable == 0
    assert h.loop.lifecycle.state is LifecycleState.FAULT
    assert h.loop.lifecycle.fault_code is code
    assert not h.loop.request("arm", timeout_s=None).accepted
    beats = h.rig.status[n_status:]
    assert beats and all(s.active_fault == code and s.state == LifecycleState.FAULT
                         for s in beats)
    repeats = h.rig.faults[n_faults:]
    assert len(repeats) == len(beats) and all(f.fault_code == code for f in repeats)


# ---------------------------------------------------------------------------- sensor frames


def test_sensor_stale(armed: LoopHarness) -> None:
    h = armed
    stale = CFG.safety.stale_ticks
    for _ in range(stale):                     # missing but within the allowance
        valves, _ = h.step(sensor=False)
        assert valves[-1].enable == 1
    valves, faults = h.step(sensor=False)      # now older than stale_ticks
    assert_faulted_now(h, valves, faults, FaultCode.SENSOR_STALE, stale + 1)
    assert_latched(h, FaultCode.SENSOR_STALE)


def test_sensor_bad_crc(armed: LoopHarness) -> None:
    valves, faults = armed.step(corrupt=True)
    assert_faulted_now(armed, valves, faults, FaultCode.SENSOR_CRC, DETAIL_SENSOR_DATA)
    assert_latched(armed, FaultCode.SENSOR_CRC)


@pytest.mark.parametrize("delta", [0, 2, 5])   # 0 = stuck counter, else frames lost
def test_sensor_counter_stuck_or_jumped(armed: LoopHarness, delta: int) -> None:
    h = armed
    h.rig.sd_counter = (h.rig.sd_counter - 1 + delta) % 16
    valves, faults = h.step()
    assert_faulted_now(h, valves, faults, FaultCode.SENSOR_COUNTER, DETAIL_SENSOR_DATA)


@pytest.mark.parametrize(("signal", "value", "code", "detail"), [
    ("rattlespace_m", 0.12, FaultCode.SENSOR_RANGE, DETAIL_RATTLESPACE),
    ("rattlespace_m", -0.15, FaultCode.SENSOR_RANGE, DETAIL_RATTLESPACE),
    ("force_n", 15500.0, FaultCode.SENSOR_RANGE, DETAIL_FORCE),
    ("accel_mps2", -155.0, FaultCode.SENSOR_RANGE, DETAIL_ACCEL),
])
def test_sensor_out_of_range(armed: LoopHarness, signal: str, value: float,
                             code: FaultCode, detail: int) -> None:
    kw: dict[str, Any] = {signal: value}
    valves, faults = armed.step(**kw)
    assert_faulted_now(armed, valves, faults, code, detail)
    # the bad value never reached the bank
    assert value not in armed.rt.inputs


@pytest.mark.parametrize("bits", [1, 2, 4, 7])
def test_sensor_status_bits(armed: LoopHarness, bits: int) -> None:
    valves, faults = _step_status(armed, bits)
    assert_faulted_now(armed, valves, faults, FaultCode.SENSOR_STATUS, bits)


def _step_status(h: LoopHarness, bits: int) -> tuple[list[Any], list[Any]]:
    h.rig.sensor(status=bits)
    h.loop.tick(h.t_ns)
    h.t_ns += 1_000_000
    return h.rig.read()


# ---------------------------------------------------------------------------- rig status


@pytest.mark.parametrize(("kw", "code"), [
    ({"watchdog": 1}, FaultCode.RIG_WATCHDOG),
    ({"supply_ok": 0}, FaultCode.SUPPLY_LOSS),
])
def test_rig_status_faults(armed: LoopHarness, kw: dict[str, int], code: FaultCode) -> None:
    h = armed
    h.rig.sensor()
    h.rig.rig_status(**kw)
    h.loop.tick(h.t_ns)
    valves, faults = h.rig.read()
    assert_faulted_now(h, valves, faults, code)


def test_rig_status_bad_crc(armed: LoopHarness) -> None:
    h = armed
    h.rig.sensor()
    msg = can.Message(arbitration_id=0x200, data=bytes(8), is_extended_id=False)
    h.rig.bus.send(msg)
    h.loop.tick(h.t_ns)
    valves, faults = h.rig.read()
    assert_faulted_now(h, valves, faults, FaultCode.SENSOR_CRC, DETAIL_RIG_STATUS)


def test_reset_refused_while_supply_loss_persists_between_rig_status_frames(
        armed: LoopHarness) -> None:
    """RigStatus comes every 10th tick: on the ticks between, the supply loss the last
    RigStatus reported still holds, so a reset is refused until a RigStatus says the
    supply is back."""
    h = armed
    h.step(status=False)
    h.rig.sensor()
    h.rig.rig_status(supply_ok=0)
    h.loop.tick(h.t_ns)
    h.t_ns += 1_000_000
    h.rig.read()
    assert h.loop.lifecycle.fault_code is FaultCode.SUPPLY_LOSS
    for _ in range(5):                                   # ticks without a RigStatus
        h.step(status=False)
        res = h.loop.request("reset", timeout_s=None)
        assert not res.accepted and "SUPPLY_LOSS" in res.message
        assert not h.loop.request("arm", timeout_s=None).accepted
    h.step(status=True)                                  # RigStatus: supply back
    h.step(status=False)
    assert h.loop.request("reset", timeout_s=None).accepted
    h.run(10, status=False)
    assert h.loop.request("arm", timeout_s=None).accepted


def test_stale_rig_status_refuses_arm_and_reset(armed: LoopHarness) -> None:
    h = armed
    limit = h.loop.cfg.safety.rig_status_stale_ticks
    assert h.loop.request("disarm", timeout_s=None).accepted
    h.step(status=True)
    h.run(limit - 1, status=False)                       # age == limit: still fresh enough
    assert h.loop.request("arm", timeout_s=None).accepted
    assert h.loop.request("disarm", timeout_s=None).accepted
    h.run(2, status=False)                               # age > limit
    res = h.loop.request("arm", timeout_s=None)
    assert not res.accepted and "RigStatus stale" in res.message
    h.rig.sensor(status=1)                               # any fault, then try to reset
    h.loop.tick(h.t_ns)
    h.t_ns += 1_000_000
    h.run(3, status=False)
    assert h.loop.lifecycle.state is LifecycleState.FAULT
    res = h.loop.request("reset", timeout_s=None)
    assert not res.accepted and "RigStatus stale" in res.message
    h.step(status=True)
    assert h.loop.request("reset", timeout_s=None).accepted


def test_no_rig_status_yet_refuses_arm() -> None:
    h = make_harness()
    try:
        h.run(30, status=False)
        res = h.loop.request("arm", timeout_s=None)
        assert not res.accepted and "no valid RigStatus" in res.message
        h.step(status=True)
        assert h.loop.request("arm", timeout_s=None).accepted
    finally:
        h.close()


# ---------------------------------------------------------------------------- frozen sensor


@pytest.mark.parametrize(("signal", "detail"), [
    ("rattlespace_m", DETAIL_RATTLESPACE),
    ("force_n", DETAIL_FORCE),
    ("accel_mps2", DETAIL_ACCEL),
])
def test_frozen_sensor_value(armed: LoopHarness, signal: str, detail: int) -> None:
    """One value bit-identical in ``frozen_ticks`` + 1 consecutive frames (counter
    advancing, the others varying): SENSOR_FROZEN at exactly that frame (not one
    earlier), safe command in the same tick."""
    h = armed
    limit = h.loop.cfg.safety.frozen_ticks
    value = {"rattlespace_m": 0.0021, "force_n": -37.5, "accel_mps2": 0.42}[signal]
    frozen: dict[str, Any] = {signal: value}
    for _ in range(limit):                    # limit identical frames: fine
        valves, _ = h.step(**frozen)
        assert valves[-1].enable == 1
    valves, faults = h.step(**frozen)          # limit + 1 identical frames
    assert_faulted_now(h, valves, faults, FaultCode.SENSOR_FROZEN, detail)
    assert not h.loop.request("reset", timeout_s=None).accepted   # still frozen
    h.step(**frozen)
    assert not h.loop.request("reset", timeout_s=None).accepted
    h.step()                                            # moves again
    assert h.loop.request("reset", timeout_s=None).accepted


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([1e-3, 2e-3, -0.0125]), min_size=1, max_size=40),
       st.integers(2, 6))
def test_frozen_monitor_matches_reference(seq: list[float], limit: int) -> None:
    """SENSOR_FROZEN iff the rattlespace value was identical in more than ``limit``
    consecutive frames (reference: direct run length), others varying."""
    cfg = default_config().replace(safety={"frozen_ticks": limit})
    mon = FaultMonitor(cfg)
    flagged = []
    for k, v in enumerate(seq):
        mon.begin_tick()
        mon.sensor_frame(True, k & 0xF, 0, v, float(k), float(-k) * 1e-2)
        flagged.append(mon.code is FaultCode.SENSOR_FROZEN)
    ref = [len(set(seq[max(0, k - limit):k + 1])) == 1 and k >= limit
           for k in range(len(seq))]
    assert flagged == ref


# ---------------------------------------------------------------------------- estimator


@pytest.mark.parametrize(("flags", "code", "detail"), [
    (1, FaultCode.NONFINITE, DETAIL_ESTIMATOR),       # StepFlag.NONFINITE_INPUT
    (2, FaultCode.NONFINITE, DETAIL_ESTIMATOR),       # StepFlag.NONFINITE_STATE
    (8, FaultCode.ESTIMATOR_DIVERGED, 0),             # StepFlag.DIVERGED
])
def test_estimator_flags(armed: LoopHarness, flags: int, code: FaultCode,
                         detail: int) -> None:
    h = armed
    resets = h.rt.resets
    original = h.rt.step

    def bad_step(*a: float) -> float:
        h.rt.flags = flags
        return 0.0 if flags & 3 else original(*a)

    h.rt.step = bad_step
    valves, faults = h.step()
    assert_faulted_now(h, valves, faults, code, detail)
    if flags & 3:
        assert h.rt.resets == resets + 1     # estimator restarted warm


def test_nonfinite_estimate_output(armed: LoopHarness) -> None:
    armed.rt.output = math.nan
    valves, faults = armed.step()
    assert_faulted_now(armed, valves, faults, FaultCode.NONFINITE, DETAIL_OUTPUT)
    armed.rt.output = math.inf
    assert_latched(armed, FaultCode.NONFINITE)


def test_degraded_estimator_is_reported_not_latched(armed: LoopHarness) -> None:
    """StepFlag.DEGRADED (the bank's conservative law) is no fault: the loop stays
    ACTIVE with the valve enabled, reports ESTIMATOR_DEGRADED in the heartbeat's
    ActiveFault while it lasts, records a note at each change, and a real fault during
    it still reaches the safe state within the tick."""
    h = armed
    events = h.capture_events()
    every = h.loop.heartbeat_every
    h.rt.flags = 16                                   # StepFlag.DEGRADED
    for _ in range(2 * every):
        valves, faults = h.step()
        assert valves[-1].enable == 1 and not faults
    assert h.loop.lifecycle.state is LifecycleState.ACTIVE
    assert h.rig.status[-1].active_fault == FaultCode.ESTIMATOR_DEGRADED
    assert h.rig.status[-1].state == LifecycleState.ACTIVE
    assert events == [("note", {"estimator": "degraded", "degradations": 1})]
    h.rt.flags = 0                                    # re-armed
    for _ in range(2 * every):
        h.step()
    assert h.rig.status[-1].active_fault == FaultCode.NONE
    assert events[-1] == ("note", {"estimator": "re-armed", "degradations": 1})
    h.rt.flags = 16 | 8                               # degraded, then unusable: fault now
    valves, faults = h.step()
    assert_faulted_now(h, valves, faults, FaultCode.ESTIMATOR_DIVERGED, 0)


def test_exception_inside_step(armed: LoopHarness, monkeypatch: Any) -> None:
    def boom(*a: float) -> float:
        raise ZeroDivisionError("injected")

    monkeypatch.setattr(armed.rt, "step", boom)
    valves, faults = armed.step()
    assert_faulted_now(armed, valves, faults, FaultCode.EXCEPTION)
    assert "ZeroDivisionError: injected" in armed.loop.lifecycle.fault_message
    # still raising: reset refused while the condition persists
    res = armed.loop.request("reset", timeout_s=None)
    assert not res.accepted and "EXCEPTION" in res.message


def test_exception_inside_force_loop(armed: LoopHarness, monkeypatch: Any) -> None:
    monkeypatch.setattr(armed.loop.pi, "step", lambda *a: [][1])
    valves, faults = armed.step()
    assert_faulted_now(armed, valves, faults, FaultCode.EXCEPTION)


# ---------------------------------------------------------------------------- timing, bus


def test_overrun_streak(armed: LoopHarness) -> None:
    h = armed
    n = CFG.safety.overrun_streak
    late = int(CFG.safety.overrun_threshold_s * 1e9) + 1
    h.step(lateness_ns=late)
    h.step(lateness_ns=0)                     # streak broken
    for _ in range(n - 1):
        valves, _ = h.step(lateness_ns=late)
        assert valves[-1].enable == 1
    valves, faults = h.step(lateness_ns=late)
    assert_faulted_now(h, valves, faults, FaultCode.OVERRUN_STREAK, n)


@pytest.mark.parametrize(("error_class", "code"), [
    (0x040, FaultCode.BUS_OFF),     # CAN_ERR_BUSOFF
    (0x080, FaultCode.BUS_ERROR),   # CAN_ERR_BUSERROR
    (0x008, FaultCode.BUS_ERROR),   # CAN_ERR_PROT
])
def test_error_frames(error_class: int, code: FaultCode) -> None:
    h = make_harness(role=None)
    h.run(10)
    h.arm()
    h.rig.sensor()
    h.rig.bus.send(can.Message(arbitration_id=error_class, is_error_frame=True,
                               data=bytes(8), is_extended_id=False))
    h.loop.tick(h.t_ns)
    valves, faults = h.rig.read()
    assert_faulted_now(h, valves, faults, code, error_class & 0xFF)
    h.close()


def test_receive_exception(armed: LoopHarness, monkeypatch: Any) -> None:
    def broken(timeout: float | None = None) -> can.Message | None:
        raise can.CanOperationError("recv failed")

    monkeypatch.setattr(armed.loop.bus, "recv", broken)
    valves, faults = armed.step()
    assert_faulted_now(armed, valves, faults, FaultCode.BUS_ERROR)


def test_send_exception_safe_command_next_tick(armed: LoopHarness, monkeypatch: Any) -> None:
    h = armed
    real_send = h.loop.bus.send
    fail = {"n": 1}

    def flaky(msg: can.Message, timeout: float | None = None) -> None:
        if fail["n"] > 0:
            fail["n"] -= 1
            raise can.CanOperationError("Transmit buffer full", error_code=105)
        real_send(msg, timeout)

    monkeypatch.setattr(h.loop.bus, "send", flaky)
    valves, faults = h.step()                 # valve send failed: nothing on the bus ...
    assert not valves
    assert h.loop.lifecycle.state is LifecycleState.FAULT
    assert h.loop.lifecycle.fault_code is FaultCode.BUS_ERROR
    assert h.loop.lifecycle.fault_detail == DETAIL_SEND
    assert faults and faults[0].fault_code == FaultCode.BUS_ERROR   # ... the report went out
    valves, _ = h.step()                      # ... and the next tick's command is safe
    assert valves[-1].enable == 0


def test_fault_while_inactive_latches_too() -> None:
    h = make_harness()
    try:
        h.run(5)
        valves, faults = h.step(corrupt=True)
        assert_faulted_now(h, valves, faults, FaultCode.SENSOR_CRC)
    finally:
        h.close()


# ---------------------------------------------------------------------------- monitor unit


def test_first_condition_of_a_tick_wins_and_all_are_counted() -> None:
    mon = FaultMonitor(CFG)
    mon.begin_tick()
    mon.sensor_frame(True, 0, 0, 0.0, 0.0, 0.0)
    mon.rig_status(True, 0, True, False)
    mon.end_receive()
    assert mon.code is FaultCode.RIG_WATCHDOG
    assert mon.counts[FaultCode.SUPPLY_LOSS] == 1
    mon.end_tick()
    assert mon.condition is FaultCode.RIG_WATCHDOG and not mon.sensors_healthy


def test_no_stale_fault_before_the_first_frame() -> None:
    mon = FaultMonitor(CFG)
    for _ in range(100):
        mon.begin_tick()
        mon.end_receive()
        assert mon.code is FaultCode.NONE
    assert "no valid SensorData" in mon.health_problem()


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=300, deadline=None)
@given(rs=finite, force=finite, acc=finite)
def test_range_check_matches_reference(rs: float, force: float, acc: float) -> None:
    """The monitor's range verdict equals an independent statement of the rules."""
    mon = FaultMonitor(CFG)
    mon.begin_tick()
    usable = mon.sensor_frame(True, 0, 0, rs, force, acc)
    limits = [(rs, CFG.sensors.lvdt_range_m, DETAIL_RATTLESPACE),
              (force, min(CFG.sensors.load_cell_range_n, CFG.safety.force_range_n),
               DETAIL_FORCE),
              (acc, CFG.sensors.accel_range_mps2, DETAIL_ACCEL)]
    bad = [(x, d) for x, lim, d in limits if not (math.isfinite(x) and abs(x) <= lim)]
    assert usable == (not bad)
    if bad:
        x, d = bad[0]
        expect = FaultCode.SENSOR_RANGE if math.isfinite(x) else FaultCode.NONFINITE
        assert (mon.code, mon.detail) == (expect, d)
    else:
        assert mon.code is FaultCode.NONE


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 15), min_size=2, max_size=40))
def test_counter_fault_iff_not_consecutive(counters: list[int]) -> None:
    mon = FaultMonitor(CFG)
    for i, c in enumerate(counters):
        mon.begin_tick()
        mon.sensor_frame(True, c, 0, 0.0, 0.0, 0.0)
        expect_fault = i > 0 and (c - counters[i - 1]) % 16 != 1
        assert (mon.code is FaultCode.SENSOR_COUNTER) == expect_fault


# ---------------------------------------------------------------------------- emulated rig


@dataclass
class HilPair:
    """Emulated rig (RigNode + FaultSchedule) and the real loop with the real bank on one
    virtual channel, stepped alternately: rig tick k, then controller tick k."""

    node: Any
    loop: ControlLoop
    spy: can.BusABC
    buses: list[can.BusABC]
    sent: dict[int, tuple[list[ValveCommand], list[FaultReport]]]

    def step(self, n: int = 1, controller: bool = True) -> None:
        for _ in range(n):
            k = self.node.tick_count
            self.node.tick()
            if controller:                      # keyed by the controller's tick
                j = self.loop.tick_count
                self.loop.tick(k * 1_000_000)
                self.sent[j] = self._read()

    def _read(self) -> tuple[list[ValveCommand], list[FaultReport]]:
        valves, faults, _status = drain_controller_frames(self.spy, strict=False)
        return valves, faults

    def close(self) -> None:
        for b in self.buses:
            b.shutdown()


def make_hil(design: Any, faults: FaultSchedule | None = None) -> HilPair:
    from controller.runtime.bank import BankRuntime
    from hil.node import RigNode
    from hil.sim.roads import make_road

    channel = f"hil-{uuid.uuid4().hex}"
    ctl = open_bus(CFG.can, role="controller", interface="virtual", channel=channel)
    rig = open_bus(CFG.can, role="rig", interface="virtual", channel=channel)
    # no receive filters on the spy: python-can's recv(timeout=0) returns None when the
    # first queued frame fails a software filter, even if matching frames follow
    spy = open_bus(CFG.can, role=None, interface="virtual", channel=channel)
    road = make_road("rough-course", 11.176, 2.0, CFG.sample_time_s, seed=3)
    node = RigNode(rig, CFG, road, faults)
    rt = BankRuntime(design, cfg=CFG)
    loop = ControlLoop(CFG, ctl, rt, PIForceLoop.from_config(CFG),
                       warmup_ticks=20)
    return HilPair(node, loop, spy, [ctl, rig, spy], {})


ARM_TICK = 100
FAULT_TICK = 200
STALE = CFG.safety.stale_ticks


@pytest.mark.parametrize(("kind", "params", "code", "observable"), [
    ("drop", {}, FaultCode.SENSOR_STALE, FAULT_TICK + STALE),
    ("silence", {}, FaultCode.SENSOR_STALE, FAULT_TICK + STALE),
    ("delay", {"ticks": 5}, FaultCode.SENSOR_STALE, FAULT_TICK + STALE),
    ("corrupt_crc", {}, FaultCode.SENSOR_CRC, FAULT_TICK),
    ("corrupt_crc", {"frames": "status"}, FaultCode.SENSOR_CRC, FAULT_TICK),
    ("stuck_counter", {}, FaultCode.SENSOR_COUNTER, FAULT_TICK),
    ("stuck_counter", {"frames": "status"}, FaultCode.SENSOR_COUNTER, FAULT_TICK),
    ("out_of_range", {"signal": "force"}, FaultCode.SENSOR_RANGE, FAULT_TICK),
    ("out_of_range", {"signal": "accel", "value": -1e9}, FaultCode.SENSOR_RANGE, FAULT_TICK),
    ("sensor_status", {"bits": 2}, FaultCode.SENSOR_STATUS, FAULT_TICK),
    ("supply_loss", {}, FaultCode.SUPPLY_LOSS, FAULT_TICK),
])
def test_fault_schedule_on_emulated_rig(default_design: Design, kind: str,
                                        params: dict[str, Any], code: FaultCode,
                                        observable: int) -> None:
    dt = CFG.sample_time_s
    schedule = FaultSchedule.from_list(
        [(FAULT_TICK * dt, (FAULT_TICK + 50) * dt, kind, params)])
    h = make_hil(default_design, schedule)
    try:
        h.step(ARM_TICK)
        assert h.loop.request("arm", timeout_s=None).accepted
        h.step(observable - ARM_TICK)
        assert h.loop.lifecycle.state is LifecycleState.ACTIVE   # not before it is visible
        assert h.sent[observable - 1][0][-1].enable == 1
        h.step()                                   # the tick the fault becomes observable
        lc = h.loop.lifecycle
        assert lc.state is LifecycleState.FAULT and lc.fault_code is code
        assert lc.fault_tick == observable
        valves, faults = h.sent[observable]
        assert valves[-1].enable == 0 and valves[-1].spool_command == 0.0
        assert faults and faults[0].fault_code == code
        h.step()                                   # the rig applies it at its next tick
        rec = h.node.record.arrays()
        assert not rec["bypass_open"][observable]
        assert rec["bypass_open"][observable + 1] and rec["spool_applied"][observable + 1] == 0
        h.step(150)                                # window over: still latched
        assert lc.state is LifecycleState.FAULT and lc.fault_code is code
        assert all(v.enable == 0 for k in range(observable, h.node.tick_count)
                   for v in h.sent[k][0])
        assert h.loop.request("reset", timeout_s=None).accepted
        h.step(30)
        assert h.loop.request("arm", timeout_s=None).accepted
    finally:
        h.close()


def test_frozen_sensor_on_emulated_rig(default_design: Design) -> None:
    """hil.faults ``frozen_sensor``: the rig repeats its last SensorData values with the
    counter advancing; the safe command goes out in the tick the repeat count passes
    ``safety.frozen_ticks``."""
    dt = CFG.sample_time_s
    limit = CFG.safety.frozen_ticks
    schedule = FaultSchedule.from_list(
        [(FAULT_TICK * dt, (FAULT_TICK + 2 * limit) * dt, "frozen_sensor", {})])
    h = make_hil(default_design, schedule)
    # frames FAULT_TICK - 1 (the last live one) .. FAULT_TICK + k: k + 2 identical ones
    observable = FAULT_TICK + limit - 1
    try:
        h.step(ARM_TICK)
        assert h.loop.request("arm", timeout_s=None).accepted
        h.step(observable - ARM_TICK)
        assert h.loop.lifecycle.state is LifecycleState.ACTIVE
        assert h.sent[observable - 1][0][-1].enable == 1
        h.step()
        lc = h.loop.lifecycle
        assert lc.state is LifecycleState.FAULT and lc.fault_code is FaultCode.SENSOR_FROZEN
        assert lc.fault_tick == observable
        valves, faults = h.sent[observable]
        assert valves[-1].enable == 0 and valves[-1].spool_command == 0.0
        assert faults and faults[0].fault_code == FaultCode.SENSOR_FROZEN
        assert not h.loop.request("reset", timeout_s=None).accepted   # still frozen
        h.step(2 * limit)                                             # window over
        assert h.loop.request("reset", timeout_s=None).accepted
    finally:
        h.close()


def test_rig_watchdog_trip_from_controller_stall(default_design: Design) -> None:
    h = make_hil(default_design)
    try:
        h.step(ARM_TICK)
        assert h.loop.request("arm", timeout_s=None).accepted
        h.step(50)
        h.step(10, controller=False)               # controller stalls 10 ms (> 5 ms)
        assert h.node.watchdog_tripped
        # the rig flags it in its next RigStatus; the controller sees it then
        k = h.node.tick_count
        while not h.loop.lifecycle.latched:
            h.step()
        lc = h.loop.lifecycle
        assert lc.fault_code is FaultCode.RIG_WATCHDOG
        assert lc.fault_tick <= k + 10
        valves, faults = h.sent[lc.fault_tick]
        assert valves[-1].enable == 0 and faults[0].fault_code == FaultCode.RIG_WATCHDOG
        # the trip is an event (the rig holds its flag until re-enabled): once a tick has
        # passed without a new trip, reset is allowed, and arming re-enables the drive
        assert not h.loop.request("reset", timeout_s=None).accepted
        h.step()
        assert h.node.watchdog_tripped
        assert h.loop.request("reset", timeout_s=None).accepted
        h.step(30)
        assert h.loop.request("arm", timeout_s=None).accepted
        h.step(3)
        assert not h.node.watchdog_tripped
    finally:
        h.close()
