"""One end-to-end run on a real CAN interface, every party its own process:

    candump capture  |  rig hil (emulated rig)  |  rig run (service)  |  Zenoh listener

:func:`run_scenario` starts them in that order, waits for the service to finish its
``--duration`` (or stops it), stops the rest by PID and returns everything they left:
the decoded capture, the service's MCAP, the telemetry samples and the outputs.

The programs' command lines are the documented ones (README, docs/socketcan.md):
``rig hil --interface socketcan --channel vcan0 --road R --speed V --faults F`` and
``rig run --interface socketcan --channel vcan0 --arm --duration S``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from controller.config import RigConfig, config_to_toml, default_config
from tests.socketcan.capture import Decoded, decode_all
from tests.socketcan.support import (
    PYTHON,
    REPO,
    CapturedFrame,
    Child,
    Children,
    free_tcp_port,
    read_candump_log,
)
from tests.socketcan.zenoh_listener import Operator, TelemetryState

IN_UML = os.environ.get("SOCKETCAN_IN_UML") == "1"
#: The loop rate of the end-to-end runs.  A UML guest has one virtual CPU on which every
#: system call costs ~15 us (no vDSO) and a SocketCAN send ~80 us, so the rig and the
#: service together need more than 1 ms per 1 ms tick; 200 Hz leaves room.  Natively
#: (a rig computer) the configured 1 kHz is used.
RATE_HZ = float(os.environ.get("SOCKETCAN_E2E_RATE_HZ", "200" if IN_UML else "1000"))
ROAD, SPEED_MPS, SEED = "iso-c", 11.176, 4242
#: The emulated drive's watchdog.  On the rig it is 5 ms; in a UML guest the service's
#: loop stalls for up to ~1.5 s now and then (see RATE_HZ), which would trip it and the
#: service would (rightly) latch RIG_WATCHDOG.  The watchdog test trips it on purpose.
WATCHDOG_MS = float(os.environ.get("SOCKETCAN_E2E_WATCHDOG_MS", "3000" if IN_UML else "5"))
#: SCHED_FIFO priority of the emulated rig (the service asks for 50 itself): with both
#: loops real-time, the recording / telemetry threads run in the gaps, not in the loops.
RIG_RT_PRIORITY = 50
#: after the rig's first frame: time for its start-up to finish
RIG_SETTLE_S = 2.0


def e2e_config(tmp_path: Path, channel: str, **sections: dict[str, Any]) -> tuple[RigConfig, Path]:
    """The run's configuration (written to ``tmp_path/rig.toml``): socketcan on
    ``channel``, telemetry on a free loopback port with multicast scouting off, recording
    into ``tmp_path/runs``, loop at :data:`RATE_HZ` with the overrun threshold scaled to
    the period."""
    period_s = 1.0 / RATE_HZ
    base: dict[str, dict[str, Any]] = {
        "design": {"sample_rate_hz": RATE_HZ},
        "can": {"interface": "socketcan", "channel": channel},
        "telemetry": {"enabled": True, "endpoints": [f"tcp/127.0.0.1:{free_tcp_port()}"],
                      "listen": True, "mode": "peer", "multicast_scouting": False,
                      "rate_hz": 20.0, "commands_enabled": True},
        "recording": {"enabled": True, "directory": str(tmp_path / "runs")},
        # UML: system-call costs make the guest's scheduling coarse (stalls of tens of ms):
        # staleness after 100 ms and an overrun streak of 50 instead of 2 ticks / 5
        "safety": {"overrun_threshold_s": 0.5 * period_s, "stale_ticks": 20,
                   "overrun_streak": 50} if IN_UML else {},
        "sensors": {"seed": SEED},
    }
    for name, values in sections.items():
        base.setdefault(name, {}).update(values)
    cfg = default_config().replace(**base)
    path = tmp_path / "rig.toml"
    path.write_text(config_to_toml(cfg))
    return cfg, path


@dataclass
class ScenarioResult:
    capture_path: Path
    frames: list[CapturedFrame]
    decoded: list[Decoded]
    capture_drops: int
    telemetry: list[dict[str, Any]]
    recordings: list[Path]
    rig_output: str
    service_output: str
    service_status: int
    rig_status: int
    wall_s: dict[str, float] = field(default_factory=dict)
    cfg: RigConfig = field(default_factory=default_config)
    notes: dict[str, Any] = field(default_factory=dict)

    def samples(self, leaf: str) -> list[dict[str, Any]]:
        return [s["payload"] for s in self.telemetry if s["key"].endswith("/" + leaf)]


def rig_argv(cfg_path: Path, channel: str, faults: Path | None, watchdog_ms: float,
             road: str = ROAD, speed_mps: float = SPEED_MPS) -> list[str]:
    argv = [PYTHON, "-m", "rig.cli", "hil", "--config", str(cfg_path),
            "--interface", "socketcan", "--channel", channel, "--road", road,
            "--speed", str(speed_mps), "--seed", str(SEED), "--watchdog-ms", str(watchdog_ms),
            "--rt-priority", str(RIG_RT_PRIORITY)]
    if faults is not None:
        argv += ["--faults", str(faults)]
    return argv


def service_argv(cfg_path: Path, channel: str, duration_s: float | None,
                 arm: bool) -> list[str]:
    argv = [PYTHON, "-m", "rig.cli", "run", "--config", str(cfg_path),
            "--interface", "socketcan", "--channel", channel]
    if duration_s is not None:
        argv += ["--duration", str(duration_s)]
    if arm:
        argv.append("--arm")
    return argv


def run_scenario(children: Children, tmp_path: Path, cfg: RigConfig, cfg_path: Path, *,
                 duration_s: float | None, faults: list[dict[str, Any]] | None = None,
                 arm: bool = True, watchdog_ms: float | None = None,
                 during: Callable[[Scenario], None] | None = None,
                 road: str = ROAD, speed_mps: float = SPEED_MPS,
                 rig_first: bool = True) -> ScenarioResult:
    """Capture, listener, service, then (once the service loops) the rig.

    The service runs ``duration_s`` of loop time, or (None) until ``during`` returns and
    it is sent SIGTERM.  ``during(scenario)`` runs in the test while both run."""
    channel = cfg.can.channel
    wall: dict[str, float] = {}
    t_start = time.monotonic()
    capture_path = tmp_path / "capture.log"
    # candump: every data frame and every error frame, big receive buffer, drop monitor;
    # its output goes to a file (line-buffered by stdbuf so the test can follow it)
    dump = children.start("candump", ["stdbuf", "-oL", "candump", "-L", "-d", "-r", "4194304",
                                      f"{channel},0:0,#FFFFFFFF"])
    endpoint = cfg.telemetry.endpoints[0]
    tel_path = tmp_path / "telemetry.jsonl"
    listener = children.python("zenoh-listener", "-m", "tests.socketcan.zenoh_listener",
                                "--connect", endpoint, "--prefix", cfg.telemetry.key_prefix,
                                "--out", str(tel_path))
    listener.wait_for_output(r"listener subscribed", timeout_s=60)
    fault_path = None
    if faults:
        fault_path = tmp_path / "faults.json"
        fault_path.write_text(json.dumps({"seed": SEED, "faults": faults}))
    wd_ms = watchdog_ms if watchdog_ms is not None else WATCHDOG_MS
    operator = Operator(endpoint, cfg.telemetry.key_prefix)  # connects when the service is up
    # In a UML guest a starting Python process stalls the (non-preemptible) guest kernel
    # for up to seconds.  rig_first: the service starts once the rig's frames flow (its
    # start-up stalls happen before its loop runs); else the service first (the rig's
    # fault schedule then starts near the service's arming; the test resets a watchdog
    # fault the rig's start-up may cause).
    def start_rig() -> Child:
        return children.start("rig-hil", rig_argv(cfg_path, channel, fault_path, wd_ms, road,
                                                  speed_mps))

    def start_service() -> Child:
        svc = children.start("rig-run", service_argv(cfg_path, channel, duration_s, arm))
        svc.wait_for_output(r"recording to", timeout_s=180)
        return svc

    if rig_first:
        rig = start_rig()
        dump.wait_for_output(r" 100#", timeout_s=180)
        time.sleep(RIG_SETTLE_S)
        t_service = time.monotonic()
        service = start_service()
    else:
        t_service = time.monotonic()
        service = start_service()
        time.sleep(RIG_SETTLE_S)
        rig = start_rig()
    scenario = Scenario(cfg, service, rig, dump, operator, TelemetryState(tel_path))
    try:
        if during is not None:
            during(scenario)
    finally:
        operator.close()
    if duration_s is None:
        service_status = service.stop(signal.SIGTERM, grace_s=60)
    else:
        service_status = service.wait(timeout_s=duration_s + 240)
    wall["service"] = time.monotonic() - t_service
    time.sleep(0.2)
    rig_status = rig.stop(signal.SIGINT, grace_s=20)
    listener.stop(signal.SIGINT, grace_s=10)
    dump.stop(signal.SIGINT)
    wall["scenario"] = time.monotonic() - t_start
    text = dump.output()
    capture_path.write_text(text)
    frames = read_candump_log(capture_path)
    drops = max((int(m[1]) for m in re.finditer(r"total drops (\d+)", text)), default=0)
    telemetry = [json.loads(line) for line in tel_path.read_text().splitlines() if line.strip()] \
        if tel_path.exists() else []
    recordings = sorted((tmp_path / "runs").rglob("*.mcap"))
    return ScenarioResult(capture_path, frames, decode_all(frames), drops, telemetry,
                          recordings, rig.output(), service.output(), service_status,
                          rig_status, wall, cfg, scenario.notes)


@dataclass
class Scenario:
    """The running parties, for ``during`` callbacks."""

    cfg: RigConfig
    service: Child
    rig: Child
    capture: Child
    operator: Operator
    state: TelemetryState
    notes: dict[str, Any] = field(default_factory=dict)


def e2e_marks(timeout_s: int) -> list[pytest.MarkDecorator]:
    """The marks of an end-to-end module: slow, its timeout, skipped without the service."""
    return [pytest.mark.slow, pytest.mark.timeout(timeout_s),
            pytest.mark.skipif(bool(service_ready()), reason=service_ready())]


def service_ready() -> str:
    """'' if the service's command exists, else why the end-to-end tests cannot run."""
    missing = [p for p in ("rig/commands/run.py", "rig/commands/hil.py", "hil/node.py")
               if not (REPO / p).exists()]
    return f"not landed yet: {', '.join(missing)}" if missing else ""
