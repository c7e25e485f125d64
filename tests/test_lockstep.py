"""``rig demo --timing lockstep``: the service and the emulated rig in two processes on a
socket-pair wire, taking turns tick by tick (rig.rt.lockstep), make the same run, bit for
bit, as the loop and the rig stepped in one process (hil.stepped_run, with the lockstep
timing: zero lateness and compute time) and as the replay of the demo's own recording.
Nothing here depends on the host's timing: the demo runs as fast as the processes go."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from controller.config import default_config
from hil.stepped_run import record_emulated_run
from rig.recording.recorder import read_run
from rig.recording.schema import DESIGN_ATTACHMENT
from rig.replay import replay_recording
from rig.rt.hostcheck import Budget, HostCheck, summarise, verdict
from rig.rt.timing_mode import TIMINGS, checked_in_own_thread, choose_timing

ROOT = Path(__file__).resolve().parents[1]
DURATION_S = 2.0


def _frames(run: object) -> list[tuple[object, ...]]:
    return [(f.t_ns, f.tick, f.arbitration_id, f.data, f.is_rx, f.is_error_frame)
            for f in run.frames]          # type: ignore[attr-defined]


def _events(run: object) -> list[tuple[object, ...]]:
    """The events; the reason of the stop is the stopper's words (demo: the stop it
    requested at the end, stepped run: "end of recording")."""
    out: list[tuple[object, ...]] = []
    for e in run.events:                  # type: ignore[attr-defined]
        detail = e.detail
        if e.kind == "lifecycle" and detail.get("to") == "STOPPING":
            detail = {k: v for k, v in detail.items() if k != "reason"}
        out.append((e.t_ns, e.tick, e.kind, detail))
    return out


@pytest.mark.timeout(300)
def test_lockstep_demo_is_the_stepped_run_and_its_replay_bit_for_bit(tmp_path: Path) -> None:
    record = tmp_path / "demo.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "rig.cli", "demo", "--timing", "lockstep", "--max-speedup", "0",
         "--duration", str(DURATION_S), "--json", "--no-telemetry", "--record", str(record),
         "-q"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines()[0].startswith("rig demo: timing lockstep (asked for")
    summary = json.loads(proc.stdout)
    assert summary["timing_mode"] == "lockstep" and summary["faults"] == []
    assert summary["final_state"] == "STOPPING" and summary["rig_error"] is None
    assert summary["recording_dropped"] == 0 and summary["armed_at_s"] == DURATION_S / 2
    assert summary["rig"]["watchdog_trips"] == 0 and summary["rig"]["late_ticks"] == 0
    n = round(DURATION_S * 1000)
    assert summary["rig"]["ticks"] == summary["timing"]["ticks"] == n

    demo = read_run(record)
    assert demo.complete, demo.stopped_at
    cfg = default_config()
    stepped = read_run(record_emulated_run(
        tmp_path / "stepped.mcap", DURATION_S, cfg=cfg,
        design_bytes=demo.attachments[DESIGN_ATTACHMENT], arm_at_s=DURATION_S / 2,
        seed=cfg.sensors.seed, warmup_ticks=round(cfg.safety.arm_warmup_s * 1000),
        road_s=DURATION_S + 1.0, lockstep_timing=True))
    # every frame both ways, every tick record, every event: the same, times included
    assert len(demo.records) == n
    assert _frames(demo) == _frames(stepped)
    assert [r.data for r in demo.records] == [r.data for r in stepped.records]
    assert _events(demo) == _events(stepped)
    states = {r.data["lifecycle"] for r in demo.records}
    assert {"INACTIVE", "ACTIVE"} <= states

    res = replay_recording(record)
    assert res.same_controller and res.bit_exact, res.summary()
    assert res.tx_frames_compared == res.tx_frames_recorded > n


def _host_check(max_lateness_s: float, kernel: str) -> HostCheck:
    cfg = default_config()
    lat = summarise([20e-6] * 1000 + [max_lateness_s])
    budget = Budget.from_config(cfg)
    return HostCheck(lat, budget, verdict(lat, budget, realtime={}, kernel=kernel), {}, 1.0,
                     kernel)


def test_auto_timing_is_chosen_in_one_place() -> None:
    """auto: realtime only where the host check passes on a PREEMPT_RT kernel."""
    assert choose_timing("auto")[0] == "lockstep"       # not checked
    assert all(choose_timing(t) == (t, "asked for") for t in TIMINGS)
    with pytest.raises(ValueError, match="expected auto"):
        choose_timing("fast")
    rt, plain = "6.1.0-rt #1 SMP PREEMPT_RT", "6.18.44 #1 SMP PREEMPT_DYNAMIC"
    assert choose_timing("auto", lambda: _host_check(100e-6, rt))[0] == "realtime"
    timing, why = choose_timing("auto", lambda: _host_check(100e-6, plain))
    assert timing == "lockstep" and "not PREEMPT_RT" in why
    timing, why = choose_timing("auto", lambda: _host_check(7e-3, rt))
    assert timing == "lockstep" and "fails" in why and "7000 us" in why
    calls: list[int] = []
    choose_timing("lockstep", lambda: calls.append(1) or _host_check(0.0, rt))
    assert not calls                                    # asked for: no check


def test_the_auto_check_runs_in_a_thread_of_its_own() -> None:
    import threading
    me = threading.get_ident()
    seen: list[int] = []

    def check() -> HostCheck:
        seen.append(threading.get_ident())
        return _host_check(0.0, "x")

    checked_in_own_thread(check)
    assert seen and seen[0] != me
