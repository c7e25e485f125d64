"""The harness of rig demo / the loop bench (hil.harness, hil.rig_process): the emulated rig
in a process of its own on a socket-pair wire.  Behaviour only, never timing: the
configuration here tolerates a starved machine (stale / overrun limits far out, a 10 s
drive watchdog), so that a loaded CI machine changes when things happen, not what."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from controller.config import RigConfig, default_config
from hil.harness import RigHarness, RigProcessError, RigProcessOptions
from hil.rig_process import TRACE_FIELDS
from rig.recording.recorder import read_run
from rig.service.runner import ServiceOptions
from rig.wire.protocol import FaultCode, LifecycleState

ROOT = Path(__file__).resolve().parents[1]
#: a machine with no CPU to spare must not fault this configuration
PATIENT = {"safety": {"stale_ticks": 1000, "overrun_streak": 100000,
                      "rig_status_stale_ticks": 100000}}
CFG: RigConfig = default_config().replace(**PATIENT)


@pytest.fixture(scope="module")
def design_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from controller.artifact import save_design
    from hil.sim.closed_loop import cached_design

    path = tmp_path_factory.mktemp("design") / "design.npz"
    save_design(cached_design(CFG), path)
    return path


def _harness(design_path: Path, tmp_path: Path | None = None, **rig: Any) -> RigHarness:
    rec = {"record": str(tmp_path / "run.mcap")} if tmp_path else {"recording": False}
    opts = ServiceOptions(design_path=str(design_path), telemetry=False, realtime=None,
                          install_signal_handlers=False, **rec)
    rig_opts = RigProcessOptions(**{"road_s": 5.0, "watchdog_s": 10.0, "realtime": None,
                                    "trace_ticks": 20_000, **rig})
    return RigHarness(CFG, opts, rig_opts, rig_start_ticks=20)


def _operator(h: RigHarness, rig_ticks: int) -> Any:
    """Arm as soon as healthy; stop after ``rig_ticks`` rig ticks."""
    def on_tick(loop: Any) -> None:
        if h.trace.count >= rig_ticks:
            h.service.stop_event.set()
        elif loop.lifecycle.state is LifecycleState.INACTIVE and not loop.health_problem():
            loop.request("arm", timeout_s=None)
    return on_tick


@pytest.mark.timeout(300)
def test_rig_process_runs_the_plant_against_the_service(design_path: Path,
                                                         tmp_path: Path) -> None:
    h = _harness(design_path, tmp_path)
    assert h.rig.pid != os.getpid()
    transitions: list[Any] = []
    h.service.loop.lifecycle.add_listener(transitions.append)
    res = h.run(on_tick=_operator(h, 1500))
    svc = h.service
    # the rig process ran, then ended when the service stopped
    assert not h.rig.alive and res.rig_error is None
    stats = res.rig_stats
    assert stats["ticks"] >= 1500 and stats["watchdog_trips"] == 0
    assert stats["bad_frames"] == 0 and stats["stale_commands"] == 0
    # it joined the bus when it started: the ~20 commands sent before were not news
    assert stats["valve_commands"] <= res.ticks_run - res.rig_started_at + 5
    # the true plant trace came back: passive until armed, then the actuator works
    tr = res.trace
    assert set(tr) == set(TRACE_FIELDS) and len(tr["accel_mps2"]) >= 1500
    armed = [t for t in transitions if t.state is LifecycleState.ACTIVE]
    assert armed, [t.reason for t in transitions]
    assert tr["bypass_open"][0] == 1.0 and (tr["bypass_open"] == 0.0).sum() > 100
    assert abs(tr["spool_applied"]).max() > 0.0
    assert not tr["watchdog_tripped"].any()
    assert not any(t.state is LifecycleState.FAULT for t in transitions)
    # the loop saw the rig's frames, and the recording holds the run
    assert svc.loop.rx_frames >= 1000
    run = read_run(tmp_path / "run.mcap")
    assert run.complete and {r.data["lifecycle"] for r in run.records} >= {"INACTIVE",
                                                                           "ACTIVE"}
    # the shutdown reached the rig before it stopped: its last command is the safe one
    last_tx = [f for f in run.frames if not f.is_rx and f.arbitration_id == 0x080][-1]
    assert last_tx.data[1] & 0x10 == 0


@pytest.mark.timeout(300)
def test_rig_process_that_dies_stops_the_run(design_path: Path) -> None:
    h = _harness(design_path)
    killed: list[int] = []

    def on_tick(loop: Any) -> None:
        if h.trace.count >= 300 and not killed:
            killed.append(loop.tick_count)
            os.kill(h.rig.pid, signal.SIGKILL)       # our own child, by its PID
    res = h.run(on_tick=on_tick)
    assert killed and res.rig_error is not None
    assert "ended" in res.rig_error or "exit status" in res.rig_error
    assert h.service.exit_reason == "emulated rig process ended"
    # the service noticed on the bus first: the wire's peer is gone = bus error
    faults = [t.fault_code for t in h.service.loop.transitions
              if t.state is LifecycleState.FAULT]
    assert faults and faults[0] in (FaultCode.BUS_ERROR, FaultCode.SENSOR_STALE)
    assert res.ticks_run < killed[0] + 10_000


def test_lockstep_rig_process_that_dies_stops_the_run_at_the_next_turn(
        design_path: Path) -> None:
    opts = ServiceOptions(design_path=str(design_path), telemetry=False, realtime=None,
                          install_signal_handlers=False, recording=False)
    rig_opts = RigProcessOptions(road_s=5.0, realtime=None, trace_ticks=20_000,
                                 lockstep=True)
    h = RigHarness(CFG, opts, rig_opts, max_speedup=0.0)
    killed: list[int] = []

    def on_tick(loop: Any) -> None:
        if killed:
            return
        assert h.trace.count == loop.tick_count      # rig tick k came before loop tick k
        if loop.tick_count >= 300:
            killed.append(loop.tick_count)
            os.kill(h.rig.pid, signal.SIGKILL)       # our own child, by its PID
    res = h.run(on_tick=on_tick)
    assert killed and res.rig_started_at == 0
    assert res.rig_error is not None and "lockstep peer" in res.rig_error
    # the loop's next turn finds the rig gone: that tick runs without it, then the run ends
    assert res.ticks_run == killed[0] + 1
    # ... where the service may notice it on the wire too (peer gone: bus error), or not
    # yet: the dying process's two ends close one after the other
    faults = [t.fault_code for t in h.service.loop.transitions
              if t.state is LifecycleState.FAULT]
    assert faults in ([], [FaultCode.BUS_ERROR])
    assert res.lockstep["stalls"] >= 0 and h.service.loop.timing.summary()["skipped"] == 0


def test_bad_road_is_reported_before_the_service_is_built(design_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    import rig.service.runner

    def no_service(*_a: Any, **_k: Any) -> None:
        raise AssertionError("the service was built although the rig could not start")

    monkeypatch.setattr(rig.service.runner, "Service", no_service)
    with pytest.raises(RigProcessError, match="nope"):
        _harness(design_path, road="nope")


@pytest.mark.timeout(120)
def test_rig_process_ends_with_the_controller_process(tmp_path: Path) -> None:
    """A controller process killed outright does not leave its emulated rig behind."""
    child = textwrap.dedent("""
        import sys, time
        from controller.config import default_config
        from hil.rig_process import RigProcess, RigProcessOptions
        from rig.bus.socketpair import socketpair_wire
        ours, theirs = socketpair_wire()
        rig = RigProcess(default_config(), RigProcessOptions(road_s=2.0, realtime=None),
                         theirs)
        rig.wait_ready()
        rig.start_at(time.monotonic_ns())
        print(rig.pid, flush=True)
        time.sleep(600)
    """)
    proc = subprocess.Popen([sys.executable, "-c", child], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert proc.stdout is not None
        rig_pid = int(proc.stdout.readline())
        os.kill(rig_pid, 0)                           # ticking
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and _exists(rig_pid):
            time.sleep(0.05)
        assert not _exists(rig_pid), "the rig process outlived its controller"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _exists(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False
