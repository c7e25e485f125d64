"""Fault injection over a real CAN interface, every fault class that can be caused from
outside the service, in one run of the service and the emulated rig (separate processes):

====================  ===========================================  ====================
expected FaultCode    injected by                                  observable on the bus
====================  ===========================================  ====================
SENSOR_CRC            rig fault schedule ``corrupt_crc``           SensorData, bad CRC
SENSOR_COUNTER        rig fault schedule ``stuck_counter``         SensorData, counter repeats
SENSOR_RANGE          rig fault schedule ``out_of_range``          Rattlespace beyond LVDT range
SENSOR_STATUS         rig fault schedule ``sensor_status``         SensorStatus != 0
SUPPLY_LOSS           rig fault schedule ``supply_loss``           RigStatus SupplyOk = 0
SENSOR_STALE          rig fault schedule ``silence``               no SensorData (stale_ticks)
BUS_ERROR             error frame (CAN_ERR_BUSERROR) from the test  the error frame
BUS_OFF               error frame (CAN_ERR_BUSOFF) from the test    the error frame
RIG_WATCHDOG          SIGSTOP of the service > drive watchdog       RigStatus WatchdogTripped
SHUTDOWN              SIGTERM of the service                        --
====================  ===========================================  ====================

Not injectable from outside the service, covered by the unit tests of rig/loop.py and
rig/safety.py: NONFINITE (CAN signals are scaled integers, they cannot carry NaN),
ESTIMATOR_DIVERGED, OVERRUN_STREAK (the service's own timing), EXCEPTION.

After each fault the test resets and re-arms the service over Zenoh (the operator's
interface), so one run covers all classes.  Per class: the service was ACTIVE when the
fault became observable; the safe ValveCommand (Enable=0) followed within one tick
(at most one Enable=1 command after the observation, counted from the capture); a
FaultReport with the expected code; the fault in the telemetry; nothing crashed.
"""

from __future__ import annotations

import itertools
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass

import can
import pytest

from tests.socketcan import capture as cap
from tests.socketcan.harness import (
    Scenario,
    ScenarioResult,
    e2e_config,
    run_scenario,
    service_ready,
)
from tests.socketcan.support import CHANNEL, Children, record
from tests.socketcan.zenoh_listener import Operator

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900),
              pytest.mark.skipif(bool(service_ready()), reason=service_ready())]

SLOT_S = 5.0        # rig time between the rig's scheduled faults
FIRST_S = 4.0       # rig time of the first one (the service arms within ~1 s)
#: a gentle road: the faults, not the ride, are under test (and a UML guest's loop timing
#: makes the closed loop rougher than on the rig)
ROAD, SPEED_MPS = "iso-a", 5.0


@dataclass(frozen=True)
class Slot:
    code: str                           # expected FaultCode name
    schedule: dict[str, object] | None  # rig fault-schedule entry (times filled in)
    window_s: float = 0.3
    inject: str | None = None           # "busoff" / "buserror" / "sigstop" (by the test)


# the rig's scheduled faults first, then the ones the test injects
SLOTS = (
    Slot("SENSOR_CRC", {"kind": "corrupt_crc"}),
    Slot("SENSOR_COUNTER", {"kind": "stuck_counter"}),
    Slot("SENSOR_RANGE", {"kind": "out_of_range", "signal": "rattlespace", "value": 1.0}),
    Slot("SENSOR_STATUS", {"kind": "sensor_status", "bits": 1}),
    Slot("SUPPLY_LOSS", {"kind": "supply_loss"}, window_s=0.5),
    Slot("SENSOR_STALE", {"kind": "silence"}, window_s=0.6),
    Slot("BUS_ERROR", None, inject="buserror"),
    Slot("BUS_OFF", None, inject="busoff"),
    Slot("RIG_WATCHDOG", None, inject="sigstop"),
)
CAN_ERR_BUSERROR, CAN_ERR_BUSOFF = 0x080, 0x040


def _slot_start(i: int) -> float:
    return FIRST_S + SLOT_S * i


def _schedule() -> list[dict[str, object]]:
    out = []
    for i, slot in enumerate(SLOTS):
        if slot.schedule is not None:
            t0 = _slot_start(i)
            out.append({**slot.schedule, "start_s": t0, "end_s": t0 + slot.window_s})
    return out


def _inject(kind: str, scenario: Scenario, watchdog_s: float) -> float:
    """Inject from the test; returns time.time() of the injection (capture clock)."""
    if kind == "sigstop":
        pid = scenario.service.pid
        os.kill(pid, signal.SIGSTOP)
        t = time.time()
        time.sleep(max(0.3, 4 * watchdog_s))
        os.kill(pid, signal.SIGCONT)
        return t
    err = CAN_ERR_BUSERROR if kind == "buserror" else CAN_ERR_BUSOFF
    with can.Bus(interface="socketcan", channel=scenario.cfg.can.channel) as bus:
        t = time.time()
        bus.send(can.Message(arbitration_id=err, is_error_frame=True, data=bytes(8),
                             is_extended_id=False))
    return t


def _timeline(watchdog_s: float) -> Callable[[Scenario], None]:
    """Event-driven: wait for each fault to latch (status over Zenoh), then reset and
    re-arm as an operator would; inject the test's own faults when the rig's are done."""
    def during(sc: Scenario) -> None:
        op = Operator(sc.cfg.telemetry.endpoints[0], sc.cfg.telemetry.key_prefix)
        seen: list[str | None] = []
        rearmed: list[bool] = []
        try:
            if op.wait_for("ACTIVE", timeout_s=180) is None:
                raise AssertionError(f"the service never armed:\n{sc.service.output()}")
            for slot in SLOTS:
                if slot.inject is not None:
                    sc.notes.setdefault("injected", {})[slot.code] = _inject(
                        slot.inject, sc, watchdog_s)
                st = op.wait_for("FAULT", timeout_s=3 * SLOT_S + 30)
                seen.append(None if st is None else st.get("fault"))
                rearmed.append(op.until("reset", "INACTIVE", timeout_s=15.0)
                               and op.until("arm", "ACTIVE", timeout_s=15.0))
            sc.notes["t_sigterm"] = time.time()
        finally:
            sc.notes["seen"] = seen
            sc.notes["rearmed"] = rearmed
            op.close()
    return during


@pytest.fixture(scope="module")
def fault_run(tmp_path_factory: pytest.TempPathFactory) -> ScenarioResult:
    tmp = tmp_path_factory.mktemp("faults")
    kids = Children(tmp)
    try:
        cfg, cfg_path = e2e_config(tmp, CHANNEL)
        from tests.socketcan.harness import WATCHDOG_MS

        result = run_scenario(kids, tmp, cfg, cfg_path, duration_s=None, faults=_schedule(),
                              during=_timeline(WATCHDOG_MS * 1e-3), road=ROAD,
                              speed_mps=SPEED_MPS)
    finally:
        kids.stop_all()
    print("\n".join(kids.dump()))
    return result


def _observable(r: ScenarioResult, code: str, after_s: float) -> float | None:
    """Capture time at which ``code``'s condition first shows on the bus after ``after_s``."""
    cfg = r.cfg
    frames = [f for f in r.decoded if f.t_s > after_s]
    sd = cap.of(frames, cap.SENSOR_DATA)
    rs = cap.of(frames, cap.RIG_STATUS)
    if code == "SENSOR_CRC":
        hit = next((f for f in sd if not f.crc_ok), None)
    elif code == "SENSOR_COUNTER":
        hit = next((b for a, b in itertools.pairwise(sd) if a.counter == b.counter), None)
    elif code == "SENSOR_RANGE":
        hit = next((f for f in sd if f.crc_ok
                    and abs(f.signals["Rattlespace"]) > cfg.sensors.lvdt_range_m), None)
    elif code == "SENSOR_STATUS":
        hit = next((f for f in sd if f.crc_ok and int(f.signals["SensorStatus"]) != 0), None)
    elif code == "SUPPLY_LOSS":
        hit = next((f for f in rs if f.crc_ok and int(f.signals["SupplyOk"]) == 0), None)
    elif code == "RIG_WATCHDOG":
        hit = next((f for f in rs if f.crc_ok and int(f.signals["WatchdogTripped"])), None)
    elif code == "SENSOR_STALE":
        gap = cfg.safety.stale_ticks * cfg.sample_time_s
        hit = next((a for a, b in itertools.pairwise(sd) if b.t_s - a.t_s > gap), None)
    elif code in ("BUS_ERROR", "BUS_OFF"):
        bit = CAN_ERR_BUSERROR if code == "BUS_ERROR" else CAN_ERR_BUSOFF
        hit = next((f for f in frames if f.frame_id & cap.CAN_ERR_FLAG
                    and f.frame_id & bit), None)
    else:  # pragma: no cover - table above is complete
        raise AssertionError(code)
    return None if hit is None else hit.t_s


def test_every_fault_class_gives_the_safe_valve_within_one_tick(fault_run: ScenarioResult
                                                                ) -> None:
    r = fault_run
    assert r.service_status == 0, r.service_output
    assert r.rig_status == 0, r.rig_output
    assert "Traceback" not in r.service_output + r.rig_output
    assert r.capture_drops == 0
    dt = r.cfg.sample_time_s
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    armed = cap.first_armed_time(r.decoded)
    assert armed is not None, r.service_output
    after = armed
    failures = []
    for slot in SLOTS:
        t_obs = _observable(r, slot.code, after)
        if t_obs is None:
            failures.append(f"{slot.code}: never observable on the bus after {after:.3f}")
            continue
        before = [v for v in valves if v.t_s < t_obs]
        if not before or not cap.enable(before[-1]):
            failures.append(f"{slot.code}: the service was not ACTIVE when the fault showed")
            after = t_obs + 0.5
            continue
        re = cap.reaction(r.decoded, t_obs)
        # SENSOR_STALE shows only after stale_ticks without a frame: count from there
        allowed = 1 + (r.cfg.safety.stale_ticks if slot.code == "SENSOR_STALE" else 0)
        ms = 1e3 * re.reaction_s
        note = f"{re.enabled_after} Enable=1 after; FaultReport {re.fault_code}"
        record(f"fault reaction {slot.code}", ms, "ms", note)
        if re.t_safe_s is None or re.enabled_after > allowed:
            failures.append(f"{slot.code}: {re.enabled_after} enabled commands after the fault "
                            f"(allowed {allowed}), safe command at {re.t_safe_s}")
        if re.fault_code != slot.code:
            failures.append(f"{slot.code}: FaultReport says {re.fault_code}")
        elif re.t_report_s is not None and re.t_safe_s is not None \
                and re.t_report_s > re.t_safe_s + dt:
            failures.append(f"{slot.code}: FaultReport later than the safe command")
        # next slot: after the service was re-armed
        rearm = next((v.t_s for v in valves if v.t_s > (re.t_safe_s or t_obs)
                      and cap.enable(v)), None)
        after = rearm if rearm is not None else t_obs + SLOT_S
    assert r.notes.get("seen") == [slot.code for slot in SLOTS], r.notes
    assert not failures, "\n".join(failures)
    assert all(r.notes.get("rearmed", [])), f"reset / re-arm over Zenoh failed: {r.notes}"


def test_faults_are_reported_in_telemetry(fault_run: ScenarioResult) -> None:
    codes = set()
    for s in fault_run.samples("fault"):
        f = s.get("fault")
        if isinstance(f, dict):
            codes.add(f.get("code"))
    missing = {slot.code for slot in SLOTS} - codes
    assert not missing, f"fault codes never published: {sorted(missing)}"


def test_shutdown_leaves_the_valve_safe_and_reports_it(fault_run: ScenarioResult) -> None:
    r = fault_run
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    assert valves and not cap.enable(valves[-1]), "last ValveCommand not safe"
    assert str(valves[-1].signals["Lifecycle"]) == "STOPPING"
    reports = cap.of(r.decoded, cap.FAULT_REPORT)
    assert reports and str(reports[-1].signals["FaultCode"]) == "SHUTDOWN"
    t_term = r.notes.get("t_sigterm")
    if t_term is not None:
        record("SIGTERM -> last (safe) ValveCommand", 1e3 * (valves[-1].t_s - t_term), "ms")
    assert "Traceback" not in r.service_output


def test_recording_survives_the_faults(fault_run: ScenarioResult) -> None:
    from rig.recording import read_run

    assert len(fault_run.recordings) == 1
    run = read_run(fault_run.recordings[0])
    assert run.complete, run.stopped_at
    faults = [e.detail for e in run.events if e.kind == "fault"]
    assert len(faults) >= len(SLOTS), faults
    assert all(t.data.get("dropped_recording", 0) == 0 for t in run.records[-5:])
