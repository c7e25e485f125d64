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

Not injectable from outside the service, covered by the unit tests of rig/service/loop.py and
rig/service/safety.py: NONFINITE (CAN signals are scaled integers, they cannot carry NaN),
ESTIMATOR_DIVERGED, OVERRUN_STREAK (the service's own timing), EXCEPTION.

After each fault the test resets and re-arms the service over Zenoh (the operator's
interface), so one run covers all classes.  Per class: the service was ACTIVE when the
fault became observable; the safe ValveCommand (Enable=0) followed within one tick
(at most one Enable=1 command after the observation, counted from the capture; for
SENSOR_STALE the commands that echo the last SensorData's counter, for a bad SensorData
frame those not computed from frames older than the last good one); a
FaultReport with the expected code; the fault in the telemetry; nothing crashed.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from tests.socketcan import capture as cap
from tests.socketcan.harness import (
    WATCHDOG_MS,
    Scenario,
    ScenarioResult,
    e2e_config,
    e2e_marks,
    run_scenario,
)
from tests.socketcan.support import CHANNEL, Children, record

pytestmark = e2e_marks(900)

SLOT_S = 4.0        # rig time between the rig's scheduled fault windows
FIRST_S = 8.0       # rig time of the first one (the service arms within a few s)
ROUNDS = 3          # each scheduled class three times: a UML stall may mask a window,
                    # and a slow re-arm after a fault masks the window right after it
ATTEMPTS = 3        # injected classes: tries until one hits an ACTIVE service
#: a gentle road: the faults, not the ride, are under test (and a UML guest's loop timing
#: makes the closed loop rougher than on the rig)
ROAD, SPEED_MPS = "iso-a", 5.0


@dataclass(frozen=True)
class Slot:
    code: str                           # expected FaultCode name
    schedule: dict[str, object] | None  # rig fault-schedule entry (times filled in)
    window_s: float = 0.3
    inject: str | None = None           # "busoff" / "buserror" / "sigstop" (by the test)


SCHEDULED = (
    Slot("SENSOR_CRC", {"kind": "corrupt_crc"}),
    Slot("SENSOR_COUNTER", {"kind": "stuck_counter"}),
    Slot("SENSOR_RANGE", {"kind": "out_of_range", "signal": "rattlespace", "value": 1.0}),
    Slot("SENSOR_STATUS", {"kind": "sensor_status", "bits": 1}),
    Slot("SUPPLY_LOSS", {"kind": "supply_loss"}, window_s=0.5),
)
#: silence last: SensorData frames counted as rig ticks stop counting during it
SILENCE = Slot("SENSOR_STALE", {"kind": "silence"}, window_s=0.8)
INJECTED = (
    Slot("BUS_ERROR", None, inject="buserror"),
    Slot("BUS_OFF", None, inject="busoff"),
    Slot("RIG_WATCHDOG", None, inject="sigstop"),
)
SLOTS = (*SCHEDULED, SILENCE, *INJECTED)
#: classes a bad SensorData frame causes (its SensorCounterEcho tells what a command
#: was computed from)
FRAME_BORNE = ("SENSOR_CRC", "SENSOR_COUNTER", "SENSOR_RANGE", "SENSOR_STATUS")
#: SensorData frames before the last good one whose echoes mark a command computed
#: before it (fewer than the 4-bit counter's 16, so no echo is ambiguous)
OLDER_FRAMES = 8
CAN_ERR_BUSERROR, CAN_ERR_BUSOFF = 0x080, 0x040


def _windows() -> list[tuple[Slot, float]]:
    """(slot, rig start time) of every scheduled window, in time order.  Round r starts
    the class sequence at its r-th class, so no class always follows the same fault (the
    window after a latched fault is the one a slow re-arm misses)."""
    n = len(SCHEDULED)
    order = [*(SCHEDULED[(r + i) % n] for r in range(ROUNDS) for i in range(n)),
             *([SILENCE] * ROUNDS)]
    return [(slot, FIRST_S + SLOT_S * i) for i, slot in enumerate(order)]


def _schedule() -> list[dict[str, object]]:
    return [{**slot.schedule, "start_s": t0, "end_s": t0 + slot.window_s}
            for slot, t0 in _windows() if slot.schedule is not None]


def _inject(kind: str, scenario: Scenario, watchdog_s: float) -> float:
    """Inject from the test; returns time.time() of the injection (capture clock)."""
    if kind == "sigstop":
        pid = scenario.service.pid
        os.kill(pid, signal.SIGSTOP)
        t = time.time()
        time.sleep(2 * watchdog_s + 0.2)
        os.kill(pid, signal.SIGCONT)
        scenario.notes["t_sigcont"] = time.time()
        return t
    err = CAN_ERR_BUSERROR if kind == "buserror" else CAN_ERR_BUSOFF
    with can.Bus(interface="socketcan", channel=scenario.cfg.can.channel) as bus:
        t = time.time()
        bus.send(can.Message(arbitration_id=err, is_error_frame=True, data=bytes(8),
                             is_extended_id=False))
    return t


def _timeline(watchdog_s: float) -> Callable[[Scenario], None]:
    """The operator's side: keep the service armed through the rig's scheduled windows
    (reset + arm over Zenoh after every fault, the state followed through telemetry),
    then inject the test's own faults into an ACTIVE service, retrying when another
    fault got there first."""
    def during(sc: Scenario) -> None:
        op, state = sc.operator, sc.state
        latched: list[str | None] = []
        sd_frames = CaptureCounter(sc.capture.log_path)
        end_rig_s = _windows()[-1][1] + SILENCE.window_s + 2.0
        need = round(end_rig_s * sc.cfg.design.sample_rate_hz
                     - ROUNDS * SILENCE.window_s * sc.cfg.design.sample_rate_hz)
        deadline = time.monotonic() + 6 * end_rig_s + 120
        try:
            if not op.recover(state, timeout_s=90.0):
                raise AssertionError(f"the service never armed:\n{sc.service.output()}")
            while sd_frames() < need:
                if time.monotonic() > deadline:
                    raise AssertionError("the rig's fault schedule did not complete")
                lifecycle, code = state()
                if lifecycle == "FAULT" and code is not None:
                    latched.append(code)
                    op.recover(state, timeout_s=20.0)
                time.sleep(0.1)
            for slot in INJECTED:
                for _ in range(ATTEMPTS):
                    op.recover(state, timeout_s=30.0)
                    sc.notes.setdefault("injected", {}).setdefault(slot.code, []).append(
                        _inject(str(slot.inject), sc, watchdog_s))
                    _, code = state.wait_for("FAULT", timeout_s=20.0)
                    latched.append(code)
                    if code == slot.code:
                        break
            op.recover(state, timeout_s=30.0)
            sc.notes["t_sigterm"] = time.time()
        finally:
            sc.notes["latched"] = latched
    return during


class CaptureCounter:
    """SensorData frames in the growing candump output (read incrementally)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = 0
        self.count = 0

    def __call__(self) -> int:
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            chunk = fh.read()
        cut = chunk.rfind(b"\n") + 1
        self.offset += cut
        self.count += chunk[:cut].count(b" 100#")
        return self.count


@pytest.fixture(scope="module")
def fault_run(tmp_path_factory: pytest.TempPathFactory) -> ScenarioResult:
    tmp = tmp_path_factory.mktemp("faults")
    kids = Children(tmp)
    try:
        # a soft actuator authority: the faults, not the ride, are under test (in a UML
        # guest the irregular loop timing makes the full-authority closed loop rough
        # enough to saturate the LVDT, a SENSOR_STATUS fault of its own)
        cfg, cfg_path = e2e_config(tmp, CHANNEL,
                                   force_loop={"output_limit": 0.02, "force_limit_n": 300.0})
        result = run_scenario(kids, tmp, cfg, cfg_path, duration_s=None, faults=_schedule(),
                              during=_timeline(WATCHDOG_MS * 1e-3), road=ROAD,
                              speed_mps=SPEED_MPS, rig_first=False)
    finally:
        kids.stop_all()
    # the processes' outputs are in the result (and in tmp); a failing test prints them
    return result


def _observable(r: ScenarioResult, code: str, after_s: float, until_s: float
                ) -> float | None:
    """Capture time at which ``code``'s condition first shows on the bus in
    (``after_s``, ``until_s``)."""
    cfg = r.cfg
    frames = [f for f in r.decoded if after_s < f.t_s < until_s]
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


def _exercises(r: ScenarioResult) -> dict[str, list[float]]:
    """Capture times from which to look for each class's onsets: the rig's scheduled
    windows (rig tick = SensorData index) and the test's injections."""
    sd_t = [f.t_s for f in cap.of(r.decoded, cap.SENSOR_DATA)]
    rate = r.cfg.design.sample_rate_hz
    out: dict[str, list[float]] = {}
    for slot, t0 in _windows():
        k = round(t0 * rate) - 2
        if slot is SILENCE:  # frames missing in earlier silences shift the index
            k -= round(sum(s.window_s for s, t in _windows() if s is SILENCE and t < t0)
                       * rate) + 2
        if 0 <= k < len(sd_t):
            out.setdefault(slot.code, []).append(sd_t[k])
    for code, times in r.notes.get("injected", {}).items():
        out[code] = [t - 0.005 for t in times]
    return out


def test_every_fault_class_gives_the_safe_valve_within_one_tick(fault_run: ScenarioResult
                                                                ) -> None:
    """For every class at least one onset hit an ACTIVE service (a UML stall can get
    another fault in first); every onset that did must give the safe ValveCommand within
    one tick and the class's FaultReport."""
    r = fault_run
    assert r.service_status == 0, r.service_output
    assert r.rig_status == 0, r.rig_output
    assert "Traceback" not in r.service_output + r.rig_output
    assert r.capture_drops == 0
    dt = r.cfg.sample_time_s
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    failures = []
    exercised: dict[str, int] = {}
    for code, starts in _exercises(r).items():
        for t_from in starts:
            # the watchdog trips only after WATCHDOG_MS of the service being stopped
            span = 3.0 + (2 * WATCHDOG_MS * 1e-3 + 0.2 if code == "RIG_WATCHDOG" else 0.0)
            t_obs = _observable(r, code, t_from, t_from + span)
            if t_obs is None:
                continue
            before = [v for v in valves if v.t_s < t_obs]
            if not before or not cap.enable(before[-1]):
                continue  # the service was not ACTIVE: not an exercise of this class
            re = cap.reaction(r.decoded, t_obs)
            allowed = 1 + (r.cfg.safety.stale_ticks if code == "SENSOR_STALE" else 0)
            if code == "SENSOR_STALE" and re.t_safe_s is not None:
                # counted in the service's own ticks, not from the capture's time: the
                # enabled commands that echo the last SensorData's counter (sent while the
                # service held that frame); a frame the service received late (UML stalls
                # the processes) would otherwise add commands computed from older data
                last = next(f for f in cap.of(r.decoded, cap.SENSOR_DATA) if f.t_s == t_obs)
                held = [v for v in valves if t_obs <= v.t_s < re.t_safe_s and cap.enable(v)
                        and int(v.signals["SensorCounterEcho"]) == last.counter]
                re = dataclasses.replace(re, enabled_after=len(held))
            elif code in FRAME_BORNE and re.t_safe_s is not None:
                # the same for a bad SensorData frame: enabled commands delivered after it
                # that echo a frame older than the last good one before it were computed
                # before the service had even that one (a guest stall that holds the
                # service's ticks delivers them late: once 4 such commands after a stuck
                # counter).  Counted: the command from the last good frame, and any the
                # service computed after reading the bad one
                sd = cap.of(r.decoded, cap.SENSOR_DATA)
                i = next(k for k, f in enumerate(sd) if f.t_s == t_obs)
                older = ({f.counter for f in sd[max(0, i - 1 - OLDER_FRAMES):max(0, i - 1)]}
                         - {sd[i].counter, sd[i - 1].counter if i else -1})
                held = [v for v in valves if t_obs <= v.t_s < re.t_safe_s and cap.enable(v)
                        and int(v.signals["SensorCounterEcho"]) not in older]
                re = dataclasses.replace(re, enabled_after=len(held))
            note = f"{re.enabled_after} Enable=1 after; FaultReport {re.fault_code}"
            if code == "SENSOR_STALE":
                note += f"; from the last SensorData, stale_ticks = {r.cfg.safety.stale_ticks}"
            if code == "RIG_WATCHDOG":
                note += "; the service was stopped when the rig's watchdog tripped"
            if re.fault_code != code:
                # another condition latched first in the same tick (e.g. after a stall)
                note += " (another fault first: not counted)"
                record(f"fault reaction {code} #{exercised.get(code, 0) + 1}",
                       1e3 * re.reaction_s, "ms", note)
                continue
            exercised[code] = exercised.get(code, 0) + 1
            record(f"fault reaction {code} #{exercised[code]}", 1e3 * re.reaction_s, "ms",
                   note)
            if re.t_safe_s is None or re.enabled_after > allowed:
                failures.append(f"{code}: {re.enabled_after} enabled commands after the "
                                f"fault (allowed {allowed}), safe command at {re.t_safe_s}")
            elif re.t_report_s is not None and re.t_report_s > re.t_safe_s + dt:
                failures.append(f"{code}: FaultReport later than the safe command")
    missing = [s.code for s in SLOTS if not exercised.get(s.code)]
    record("faults latched in the run", len(r.notes.get("latched", [])), "",
           ", ".join(str(c) for c in r.notes.get("latched", [])))
    assert not missing, f"classes never exercised on an ACTIVE service: {missing}; {r.notes}"
    assert not failures, "\n".join(failures)


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
    from rig.recording.recorder import read_run

    assert len(fault_run.recordings) == 1
    run = read_run(fault_run.recordings[0])
    assert run.complete, run.stopped_at
    faults = [e.detail for e in run.events if e.kind == "fault"]
    assert len(faults) >= len(SLOTS), faults
    assert all(t.data.get("dropped_recording", 0) == 0 for t in run.records[-5:])
