"""Lifecycle: valid and refused transitions, on the state machine and through the loop."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from rig.service.lifecycle import Lifecycle, Transition
from rig.wire.protocol import FaultCode, LifecycleState
from tests.support.loop_harness import LoopHarness, make_harness

S = LifecycleState
CFG = default_config()


# ---------------------------------------------------------------------------- state machine


def test_valid_path_and_listener_record() -> None:
    lc = Lifecycle()
    seen: list[Transition] = []
    lc.add_listener(seen.append)
    assert lc.state is S.INACTIVE and not lc.valve_enabled
    assert lc.arm(1, 10, healthy=True).accepted and lc.valve_enabled
    assert lc.fault(FaultCode.SENSOR_CRC, 2, 20, detail=1, message="bad crc")
    assert lc.state is S.FAULT and not lc.valve_enabled
    assert (lc.fault_code, lc.fault_tick, lc.fault_detail) == (FaultCode.SENSOR_CRC, 2, 1)
    assert lc.reset(3, 30, condition=FaultCode.NONE).accepted
    assert lc.state is S.INACTIVE and lc.fault_code is FaultCode.NONE
    assert lc.arm(4, 40, healthy=True).accepted
    assert lc.disarm(5, 50).accepted and lc.state is S.INACTIVE
    lc.stop(6, 60)
    assert lc.state is S.STOPPING
    assert [(t.previous, t.state) for t in seen] == [
        (S.INACTIVE, S.ACTIVE), (S.ACTIVE, S.FAULT), (S.FAULT, S.INACTIVE),
        (S.INACTIVE, S.ACTIVE), (S.ACTIVE, S.INACTIVE), (S.INACTIVE, S.STOPPING)]
    assert seen[1].fault_code is FaultCode.SENSOR_CRC and seen[1].tick == 2
    assert seen[1].as_dict()["fault"] == "SENSOR_CRC"


def test_refusals() -> None:
    lc = Lifecycle()
    res = lc.arm(0, 0, healthy=False, why_not="SensorData stale")
    assert not res.accepted and "stale" in res.message and lc.state is S.INACTIVE
    lc.fault(FaultCode.SENSOR_STALE, 1, 1)
    assert not lc.arm(2, 2, healthy=True).accepted             # latched: no arm from FAULT
    assert not lc.disarm(2, 2).accepted                         # disarm does not clear it
    res = lc.reset(3, 3, condition=FaultCode.SENSOR_STALE)      # condition still present
    assert not res.accepted and "SENSOR_STALE" in res.message and lc.state is S.FAULT
    assert not lc.fault(FaultCode.EXCEPTION, 4, 4)              # the first fault stays
    assert lc.fault_code is FaultCode.SENSOR_STALE
    lc.stop(5, 5)
    assert not lc.reset(6, 6, FaultCode.NONE).accepted          # STOPPING is final
    assert not lc.arm(6, 6, True).accepted
    assert not lc.fault(FaultCode.EXCEPTION, 6, 6)
    assert lc.state is S.STOPPING


def test_listener_exception_does_not_break_the_transition() -> None:
    lc = Lifecycle()

    def bad(_: Transition) -> None:
        raise RuntimeError("listener")

    lc.add_listener(bad)
    assert lc.fault(FaultCode.EXCEPTION, 0, 0)
    assert lc.state is S.FAULT


EVENTS = st.sampled_from(["arm_ok", "arm_bad", "disarm", "fault", "reset_ok", "reset_bad",
                          "stop"])


@settings(max_examples=300, deadline=None)
@given(st.lists(EVENTS, max_size=30))
def test_against_reference_model(events: list[str]) -> None:
    """Random event sequences vs. a table of the documented transitions."""
    table = {
        (S.INACTIVE, "arm_ok"): S.ACTIVE, (S.ACTIVE, "disarm"): S.INACTIVE,
        (S.INACTIVE, "fault"): S.FAULT, (S.ACTIVE, "fault"): S.FAULT,
        (S.FAULT, "reset_ok"): S.INACTIVE,
    }
    lc = Lifecycle()
    ref = S.INACTIVE
    for i, ev in enumerate(events):
        if ev == "arm_ok":
            lc.arm(i, i, True)
        elif ev == "arm_bad":
            lc.arm(i, i, False, "no")
        elif ev == "disarm":
            lc.disarm(i, i)
        elif ev == "fault":
            lc.fault(FaultCode.BUS_ERROR, i, i)
        elif ev == "reset_ok":
            lc.reset(i, i, FaultCode.NONE)
        elif ev == "reset_bad":
            lc.reset(i, i, FaultCode.BUS_ERROR)
        else:
            lc.stop(i, i)
        ref = S.STOPPING if ev == "stop" else table.get((ref, ev), ref)
        assert lc.state is ref
        assert lc.valve_enabled == (ref is S.ACTIVE)
        assert (lc.fault_code is not FaultCode.NONE) == (ref is S.FAULT or (
            ref is S.STOPPING and lc.fault_code is not FaultCode.NONE))


# ---------------------------------------------------------------------------- through the loop


@pytest.fixture
def h() -> Any:
    harness = make_harness(warmup_ticks=20)
    yield harness
    harness.close()


def test_arm_refused_without_sensor_data(h: LoopHarness) -> None:
    h.run(30, sensor=False)
    res = h.loop.request("arm", timeout_s=None)
    assert not res.accepted and "no valid SensorData" in res.message
    assert h.rig.valve[-1].enable == 0


def test_arm_refused_while_estimator_warms_up(h: LoopHarness) -> None:
    h.run(10)
    res = h.loop.request("arm", timeout_s=None)
    assert not res.accepted and "warming up" in res.message
    h.run(10)
    assert h.loop.request("arm", timeout_s=None).accepted


def test_arm_refused_with_stale_sensors_and_reset_refused_while_stale(h: LoopHarness) -> None:
    h.run(30)
    h.run(CFG.safety.stale_ticks + 1, sensor=False)       # stale while INACTIVE: latched
    assert h.loop.lifecycle.state is S.FAULT
    assert h.loop.lifecycle.fault_code is FaultCode.SENSOR_STALE
    res = h.loop.request("arm", timeout_s=None)
    assert not res.accepted
    for _ in range(5):                                      # still stale: reset refused
        h.step(sensor=False)
        res = h.loop.request("reset", timeout_s=None)
        assert not res.accepted and "SENSOR_STALE" in res.message
    h.step()                                                # data back: condition gone
    assert h.loop.request("reset", timeout_s=None).accepted
    assert h.loop.lifecycle.state is S.INACTIVE
    assert h.rt.resets >= 1                                 # estimator restarted on reset
    res = h.loop.request("arm", timeout_s=None)             # warm-up starts again
    assert not res.accepted and "warming up" in res.message
    h.run(20)
    assert h.loop.request("arm", timeout_s=None).accepted
    valves, _ = h.step()
    assert valves[-1].enable == 1


def test_arm_refused_on_supply_loss(h: LoopHarness) -> None:
    h.run(30)
    h.rig.sensor()
    h.rig.rig_status(supply_ok=0)
    h.loop.tick(h.t_ns)
    h.rig.read()
    assert h.loop.lifecycle.state is S.FAULT
    h.rig.sensor()
    h.rig.rig_status(supply_ok=0)
    h.loop.tick(h.t_ns + 1_000_000)
    assert not h.loop.request("reset", timeout_s=None).accepted   # supply still lost


def test_shutdown_sends_safe_command_and_shutdown_report(h: LoopHarness) -> None:
    h.run(30)
    h.arm()
    h.step(rattlespace_m=0.01)
    assert h.rig.valve[-1].enable == 1
    h.loop.shutdown("test")
    valves, faults = h.rig.read()
    assert valves[-1].enable == 0 and valves[-1].lifecycle == S.STOPPING
    assert faults[-1].fault_code == FaultCode.SHUTDOWN and faults[-1].fault_state == S.STOPPING
    assert h.loop.lifecycle.state is S.STOPPING
