"""The loop thread's real-time set-up (rig/rt/realtime.py) does not spread to what it starts."""

from __future__ import annotations

import os
import threading
from typing import Any

import pytest

from rig.rt.realtime import RealtimeRequest, apply_realtime

#: SCHED_FIFO only: none of the process-wide measures (gc, switch interval, mlockall)
_FIFO_ONLY = RealtimeRequest(fifo_priority=1, cpus=(), lock_memory=False, timer_slack_ns=0,
                             switch_interval_s=0.0, freeze_gc=False, cpu_latency_us=None)


@pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling")
def test_a_thread_started_by_the_real_time_loop_thread_is_an_ordinary_one() -> None:
    """A thread the loop thread starts after its set-up (a helper of the service, a
    process it spawns) is SCHED_OTHER, not a real-time peer of the loop on its CPU."""
    seen: dict[str, int] = {}

    def helper() -> None:
        seen["helper"] = os.sched_getscheduler(0)

    def loop_thread() -> None:
        report = apply_realtime(_FIFO_ONLY)
        if "sched_fifo" not in report.granted:
            seen["denied"] = 1
            return
        seen["loop"] = os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        t = threading.Thread(target=helper)
        t.start()
        t.join()

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join()
    if "denied" in seen:
        pytest.skip("SCHED_FIFO refused here")
    assert seen == {"loop": os.SCHED_FIFO, "helper": os.SCHED_OTHER}


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs CPU affinity and 2 CPUs")
def test_a_helper_thread_leaves_the_loops_cpus_and_its_processes_start_off_them() -> None:
    """A helper thread started on the loop's CPUs (the service pinned, as systemd's
    CPUAffinity= does) moves to the others; a process it starts, told the loop's CPUs
    (loop_cpus_env, as a restarted telemetry process is), starts on the helper's CPUs and
    stays there when it leaves the loop's CPUs itself (without being told, it would take
    the helper's CPUs for the loop's and move onto the loop's)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from rig.recording.cpus import leave_the_loops_cpus, loop_cpus_env

    loop_cpu = min(os.sched_getaffinity(0))
    seen: dict[str, Any] = {}
    child = ("import json, os; from rig.recording.cpus import leave_the_loops_cpus; "
             "start = sorted(os.sched_getaffinity(0)); left = leave_the_loops_cpus(); "
             "print(json.dumps([start, sorted(left or ()), sorted(os.sched_getaffinity(0))]))")

    def helper() -> None:
        seen["left"] = leave_the_loops_cpus()
        seen["after"] = os.sched_getaffinity(0)
        seen["child"] = json.loads(subprocess.run(
            [sys.executable, "-c", child], env=loop_cpus_env(seen["left"]),
            cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
            check=True, timeout=60).stdout)

    def service_thread() -> None:
        os.sched_setaffinity(0, {loop_cpu})
        t = threading.Thread(target=helper)
        t.start()
        t.join()

    t = threading.Thread(target=service_thread)
    t.start()
    t.join()
    assert seen["left"] == {loop_cpu}
    assert loop_cpu not in seen["after"] and seen["after"]
    start, left, end = seen["child"]
    assert start == end == sorted(seen["after"]) and left == [loop_cpu]
