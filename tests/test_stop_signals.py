"""SIGTERM / SIGINT at any point of `rig run` and `rig demo` (rig.rt.stop_signals): exit 0, one
message, and a complete recording or none.

The set-up phases are hit exactly by sending the signal to this very process from inside
the step (the command runs in-process through rig.cli.main, which installs the
handlers); the loop phase and arbitrary moments by signalling a subprocess."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from controller.config import config_to_toml, default_config
from rig.cli import main
from rig.recording.recorder import read_run
from rig.rt.stop_signals import StopRequested, StopSignals
from tests.support.processes import killed_on_exit, sigterm_and_wait

ROOT = Path(__file__).resolve().parents[1]
CFG = default_config()


def _sigterm_self() -> None:
    os.kill(os.getpid(), signal.SIGTERM)


def _assert_nothing_recorded(directory: Path) -> None:
    assert not [p for p in directory.rglob("*.mcap")], list(directory.rglob("*"))


# ---------------------------------------------------------------------------- unit


def test_stop_signals_set_the_event_and_raise_only_when_interruptible() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals() as stop:
        _sigterm_self()
        assert stop.requested and stop.signal_name == "SIGTERM"
        with pytest.raises(StopRequested, match="SIGTERM"):
            stop.check()
    with StopSignals() as stop, pytest.raises(StopRequested) as err, stop.interruptible():
        _sigterm_self()
        for _ in range(1000):          # Python work: the handler raises in here
            time.sleep(0.01)
        pytest.fail("not interrupted")
    assert err.value.signal_name == "SIGTERM"
    with StopSignals() as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.signal_name == "SIGINT"      # no KeyboardInterrupt
    assert signal.getsignal(signal.SIGTERM) is before      # restored


# ---------------------------------------------------------------------------- set-up phases


def _patch_then_signal(monkeypatch: pytest.MonkeyPatch, target: Any, name: str,
                       before: bool) -> None:
    original: Callable[..., Any] = getattr(target, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if before:
            _sigterm_self()
        out = original(*args, **kwargs)
        if not before:
            _sigterm_self()
        return out

    monkeypatch.setattr(target, name, wrapper)


def _run_argv(design: Path | None, record: Path) -> list[str]:
    return ["run", "--interface", "virtual", "--channel", f"stop-{uuid.uuid4().hex}",
            "--no-telemetry", "--no-realtime", "--duration", "30", "--record", str(record),
            *(["--design", str(design)] if design else [])]


@pytest.mark.timeout(120)
def test_rig_run_sigterm_during_the_design(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    import controller.design

    def slow_design(cfg: Any) -> Any:
        _sigterm_self()
        for _ in range(3000):               # 30 s of "design" unless interrupted
            time.sleep(0.01)
        raise AssertionError("the design was not interrupted")

    monkeypatch.setattr(controller.design, "design_bank", slow_design)
    monkeypatch.setenv("RIG_DESIGN_CACHE", "off")   # a cached design would skip it
    t0 = time.monotonic()
    assert main(_run_argv(None, tmp_path / "run.mcap")) == 0
    assert time.monotonic() - t0 < 20
    err = capsys.readouterr().err
    assert "rig run: stopped by SIGTERM before the control loop started; nothing recorded" \
        in err and "Traceback" not in err
    _assert_nothing_recorded(tmp_path)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("phase", ["bus", "recording", "ready"])
def test_rig_run_sigterm_before_the_loop(phase: str, design_path: Path, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    import rig.bus.core
    import rig.recording.recorder
    import rig.rt.sdnotify

    target, name, before = {
        "bus": (rig.bus.core, "open_bus", True),                  # while the bus opens
        "recording": (rig.recording.recorder.RunRecorder, "__init__", False),  # writer running
        "ready": (rig.rt.sdnotify.SdNotifier, "ready", True),   # just before the first tick
    }[phase]
    _patch_then_signal(monkeypatch, target, name, before)
    assert main(_run_argv(design_path, tmp_path / "run.mcap")) == 0
    err = capsys.readouterr().err
    assert "stopped by SIGTERM before the control loop started; nothing recorded" in err
    assert "Traceback" not in err
    _assert_nothing_recorded(tmp_path)


@pytest.mark.timeout(200)
@pytest.mark.parametrize("phase", ["rig set-up", "design", "waiting for the rig"])
def test_rig_demo_sigterm_before_the_loop(phase: str, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    import controller.design
    import hil.rig_process

    if phase == "design":
        def slow_design(cfg: Any) -> Any:
            _sigterm_self()
            for _ in range(3000):
                time.sleep(0.01)
            raise AssertionError("the design was not interrupted")
        monkeypatch.setattr(controller.design, "design_bank", slow_design)
        monkeypatch.setenv("RIG_DESIGN_CACHE", "off")   # a cached design would skip it
    else:
        name = "wait_built" if phase == "rig set-up" else "wait_ready"
        _patch_then_signal(monkeypatch, hil.rig_process.RigProcess, name, True)
    record = tmp_path / "demo.mcap"
    assert main(["demo", "--duration", "3", "--quiet", "--no-telemetry", "--no-realtime",
                 "--record", str(record)]) == 0
    err = capsys.readouterr().err
    assert "rig demo: stopped by SIGTERM before the control loop started; nothing " \
           "recorded" in err and "Traceback" not in err
    _assert_nothing_recorded(tmp_path)


# ---------------------------------------------------------------------------- subprocesses


def _patient_config(tmp_path: Path) -> Path:
    path = tmp_path / "patient.toml"
    path.write_text(config_to_toml(CFG.replace(safety={
        "stale_ticks": 1000, "overrun_streak": 100000, "rig_status_stale_ticks": 100000})))
    return path


def _start(argv: list[str], tmp_path: Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NOTIFY_SOCKET", None)
    return subprocess.Popen([sys.executable, "-m", "rig.cli", *argv], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_handler(proc: subprocess.Popen[str], timeout_s: float = 60.0) -> None:
    """Until the process catches SIGTERM (its handler installed: /proc/PID/status
    SigCgt), however slowly a loaded machine starts Python."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        with open(f"/proc/{proc.pid}/status") as f:
            caught = next(int(line.split()[1], 16) for line in f
                          if line.startswith("SigCgt:"))
        if caught >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.005)
    raise AssertionError("the process never installed its SIGTERM handler")


def _wait_running(proc: subprocess.Popen[str], timeout_s: float) -> list[str]:
    """Until the demo's progress line shows rig time > 0 (the loop runs)."""
    import re

    assert proc.stderr is not None
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        m = re.match(r"t\s+([\d.]+) s", line)
        if m and float(m.group(1)) > 0:
            return lines
    proc.kill()
    raise AssertionError("the demo never ran:\n" + "".join(lines))


def _assert_complete_or_none(path: Path) -> None:
    if not path.exists():
        return
    run = read_run(path)
    assert run.complete and len(run.records) > 0, run.stopped_at


@pytest.mark.timeout(200)
def test_rig_demo_sigterm_during_the_loop(tmp_path: Path) -> None:
    record = tmp_path / "demo.mcap"
    proc = _start(["demo", "--duration", "60", "--no-telemetry", "--no-realtime", "--json",
                   "--config", str(_patient_config(tmp_path)), "--rig-watchdog-ms", "10000",
                   "--record", str(record)], tmp_path)
    with killed_on_exit(proc):
        lines = _wait_running(proc, 150)
        out, err = sigterm_and_wait(proc, 60)
    err = "".join(lines) + err
    assert proc.returncode == 0, err
    assert "rig demo: stopped by SIGTERM after" in err and "Traceback" not in err
    import json

    summary = json.loads(out)
    assert summary["stopped_by"] == "SIGTERM" and summary["final_state"] == "STOPPING"
    assert summary["passive"]["ticks"] > 0
    run = read_run(record)
    assert run.complete and len(run.records) > 0


@pytest.mark.timeout(300)
@pytest.mark.parametrize("delay_s", [0.0, 0.5, 2.0, 5.0])
def test_rig_run_sigterm_at_an_arbitrary_moment(delay_s: float, tmp_path: Path) -> None:
    """Whatever it is doing (imports, design, opening the bus or the recording, running):
    exit 0, a message, and a complete recording or none.  (Counted from the moment its
    handler is installed: before that, in the first ~0.1 s of Python's start-up, no
    program can catch SIGTERM.)"""
    record = tmp_path / "run.mcap"
    proc = _start(["run", "--interface", "virtual", "--channel", f"t-{uuid.uuid4().hex}",
                   "--no-telemetry", "--no-realtime", "--record", str(record)], tmp_path)
    with killed_on_exit(proc):
        _wait_handler(proc)
        time.sleep(delay_s)
        _out, err = sigterm_and_wait(proc, 120)
    assert proc.returncode == 0, err
    assert "rig run: stopped by SIGTERM" in err and "Traceback" not in err
    _assert_complete_or_none(record)
    if "before the control loop started" in err:
        assert not record.exists()
    else:
        assert f"recording {record} complete" in err
