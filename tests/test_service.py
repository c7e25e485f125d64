"""The service: SIGTERM in a subprocess (exit 0, valve safe, recording complete), systemd
notify protocol (READY, WATCHDOG from the loop, STOPPING), command handler, CLI errors."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import pytest

from controller.config import RigConfig, default_config
from rig.recording.recorder import read_run
from rig.rt.sdnotify import SdNotifier
from rig.service.runner import Service, ServiceOptions
from rig.wire.protocol import FaultCode, LifecycleState

ROOT = Path(__file__).resolve().parents[1]
CFG = default_config()

# the child: an emulated rig on the virtual channel (an observer independent of the
# service: it decodes what the service sent) plus `rig run` in the main thread
CHILD = textwrap.dedent("""
    import json, sys, threading
    from controller.config import default_config
    from hil.node import RigNode
    from hil.sim.roads import make_road
    from rig.bus.core import open_bus
    from rig.cli import main

    channel, record, design = sys.argv[1], sys.argv[2], sys.argv[3]
    cfg = default_config()
    bus = open_bus(cfg.can, role=None, interface="virtual", channel=channel)
    node = RigNode(bus, cfg, make_road("rough-course", 11.176, 60.0, cfg.sample_time_s))
    stop = threading.Event()
    threading.Thread(target=node.run, args=(stop,), daemon=True).start()
    rc = main(["run", "--interface", "virtual", "--channel", channel, "--arm",
               "--record", record, "--design", design, "--no-telemetry", "--no-realtime"])
    stop.set()
    node.tick()                      # drain what the service sent last
    c, f = node.command, node.fault_report
    print(json.dumps({"rc": rc, "enable": c.enable, "lifecycle": c.lifecycle,
                      "spool": c.spool_command, "fault_code": f.fault_code,
                      "fault_state": f.fault_state, "valve_commands": node.stats.valve_commands}))
    sys.exit(rc)
""")


def _wait_for(proc: subprocess.Popen[str], texts: tuple[str, ...], timeout_s: float,
              lines: list[str]) -> str:
    assert proc.stderr is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        lines.append(line)
        for text in texts:
            if text in line:
                return text
    proc.kill()
    raise AssertionError(f"{texts!r} not seen; stderr:\n{''.join(lines)}")


@pytest.mark.timeout(120)
def test_sigterm_exits_0_with_safe_valve_and_complete_recording(design_path: Path,
                                                                tmp_path: Path) -> None:
    record = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NOTIFY_SOCKET", None)
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, f"sigterm-{uuid.uuid4().hex}", str(record),
         str(design_path)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    # running and armed (valve enabled); on a heavily loaded machine a fault (e.g. the
    # rig's 5 ms drive watchdog) may latch before the arm: the shutdown path is the same
    reached = _wait_for(proc, ("-> ACTIVE", "-> FAULT"), 60.0, lines)
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, "".join(lines) + err
    seen = json.loads(out.strip().splitlines()[-1])
    assert seen["rc"] == 0 and seen["valve_commands"] > 100
    # the rig's last valid command: safe state, from a stopping controller
    assert seen["enable"] == 0 and seen["spool"] == 0.0
    assert seen["lifecycle"] == LifecycleState.STOPPING
    assert seen["fault_code"] == FaultCode.SHUTDOWN
    assert seen["fault_state"] == LifecycleState.STOPPING
    # (on a loaded machine the rig may have tripped a fault before: any state -> STOPPING)
    assert "-> STOPPING" in err and "SIGTERM" in err
    run = read_run(record)
    assert run.complete, run.stopped_at
    if reached == "-> ACTIVE":
        assert any(r.data["lifecycle"] == "ACTIVE" for r in run.records)
    last_tx = [f for f in run.frames if not f.is_rx and f.arbitration_id == 0x080][-1]
    assert last_tx.data[1] & 0x10 == 0                  # Enable bit clear
    kinds = [(e.kind, e.detail.get("to")) for e in run.events if isinstance(e.detail, dict)]
    assert ("lifecycle", "STOPPING") in kinds
    assert "config.toml" in run.attachments and "design.npz" in run.attachments


@pytest.mark.parametrize("case", ["missing_design", "no_such_bus"])
def test_run_cli_errors_exit_2(case: str, design_path: Path, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    design = str(tmp_path / "missing.npz") if case == "missing_design" else str(design_path)
    proc = subprocess.run(
        [sys.executable, "-m", "rig.cli", "run", "--interface", "socketcan", "--channel",
         "nosuchcan9", "--no-record", "--no-telemetry", "--no-realtime", "--design", design],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    expected = "missing.npz" if case == "missing_design" else "cannot open the CAN bus"
    assert expected in proc.stderr and "Traceback" not in proc.stderr


def _service(design_path: Path, cfg: RigConfig = CFG, **kw: Any) -> Service:
    opts = ServiceOptions(design_path=str(design_path), interface="virtual",
                          channel=f"svc-{uuid.uuid4().hex}", recording=False, telemetry=False,
                          realtime=None, install_signal_handlers=False, **kw)
    return Service(cfg, opts)


def test_sd_notify_ready_watchdog_from_loop_and_stopping(design_path: Path,
                                                         tmp_path: Path) -> None:
    sock_path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.settimeout(0.05)
    msgs: list[str] = []
    done = threading.Event()

    def reader() -> None:            # like systemd: read as they come (the queue is short)
        while not done.is_set():
            try:
                msgs.append(server.recv(4096).decode())
            except TimeoutError:
                continue

    th = threading.Thread(target=reader)
    th.start()
    notifier = SdNotifier.from_environment({"NOTIFY_SOCKET": sock_path,
                                            "WATCHDOG_USEC": "40000"})
    assert notifier.watchdog_period_ns == 20_000_000     # half of WATCHDOG_USEC
    svc = _service(design_path, duration_s=0.5)
    svc.notifier = notifier
    svc.loop.notifier = notifier
    svc.loop._watchdog_period_ns = notifier.watchdog_period_ns
    assert svc.run() == 0
    time.sleep(0.1)
    done.set()
    th.join()
    server.close()
    assert notifier.errors == 0
    assert msgs[0].startswith("READY=1\nSTATUS=INACTIVE")
    pings = [m for m in msgs if m == "WATCHDOG=1"]
    assert 15 <= len(pings) <= 30, len(pings)            # 0.5 s / 20 ms
    assert any(m.startswith("STOPPING=1") for m in msgs[-2:])
    assert msgs[-1] == "STATUS=STOPPING: duration" or msgs[-1].startswith("STOPPING=1")


def test_sd_notify_inert_without_socket() -> None:
    n = SdNotifier.from_environment({})
    assert not n.enabled and n.watchdog_period_ns == 0
    assert not n.ready("x") and not n.watchdog()
    other_pid = SdNotifier.from_environment({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000",
                                             "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other_pid.watchdog_period_ns == 0
    other_pid.close()


def test_command_handler_and_stop_event(design_path: Path) -> None:
    # no rig on the bus: the refusal to arm must be about the missing sensor data, so an
    # overrun streak on a busy machine (a fault of its own) must not come first
    svc = _service(design_path, CFG.replace(safety={"overrun_streak": 100000}))
    results: dict[str, Any] = {}

    def operator() -> None:
        time.sleep(0.2)
        try:
            svc.command_handler("arm", {})
        except ValueError as exc:            # no rig on the bus: refused with the reason
            results["arm"] = str(exc)
        results["blending"] = svc.command_handler("blending", {"blending": "bayes"})
        svc.stop_event.set()

    th = threading.Thread(target=operator)
    th.start()
    assert svc.run() == 0
    th.join()
    assert "no valid SensorData" in results["arm"]
    assert results["blending"] == "blending 1" and svc.runtime.blending == 1
    assert svc.exit_reason == "stop requested"
    assert svc.loop.lifecycle.state is LifecycleState.STOPPING




def test_service_says_what_the_schedule_runs_on(caplog: pytest.LogCaptureFixture) -> None:
    """The defaults (road preview on) on a bus with no rig: the service says at start-up
    what the schedule runs on with and without the rig's RoadPreview frames, and its
    status says why the preview is not live; with a fixed weight set it warns that the
    preview is unused, and with the comfort set that the travel governor takes it."""
    from controller.config import load_config
    cfg = load_config(None)
    opts = ServiceOptions(design_path=None, interface="virtual",
                          channel=f"svc-{uuid.uuid4().hex}", recording=False, telemetry=False,
                          realtime=None, install_signal_handlers=False, duration_s=0.05)
    with caplog.at_level("INFO", logger="rig.service.runner"):
        svc = Service(cfg, opts)
        assert svc.run() == 0
    assert "road preview on (0.2 s ahead)" in caplog.text
    assert svc.loop.status()["road_preview"] == "no_frame"
    assert svc.loop.status()["preview_trust"] == "settling"     # 0.05 s after the reset
    caplog.clear()
    with caplog.at_level("WARNING", logger="rig.service.runner"):
        fixed = Service(cfg, dataclasses.replace(opts, weights=1,
                                                 channel=f"svc-{uuid.uuid4().hex}"))
        assert fixed.run() == 0
    assert "design.preview_horizon_s = 0.2 s is unused: weight set 1" in caplog.text
    assert fixed.loop.status()["road_preview"] == "unused"
    assert fixed.loop.status()["preview_trust"] == "unused"
    caplog.clear()
    with caplog.at_level("INFO", logger="rig.service.runner"):
        governed = Service(cfg, dataclasses.replace(opts, weights=2,
                                                    channel=f"svc-{uuid.uuid4().hex}"))
        assert governed.run() == 0
    assert "the travel governor of weight set 2" in caplog.text
    assert governed.loop.status()["road_preview"] == "no_frame"
    assert governed.loop.status()["preview_trust"] == "governor"
