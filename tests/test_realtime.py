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
def test_a_helper_thread_leaves_the_loops_cpus_and_starts_processes_from_them() -> None:
    """A helper thread started on the loop's CPUs (the service pinned, as systemd's
    CPUAffinity= does) moves to the others; around a process it starts it is back on
    the loop's CPUs, so the process finds them and leaves them too."""
    from rig.recording.cpus import leave_the_loops_cpus, on_the_loops_cpus

    loop_cpu = min(os.sched_getaffinity(0))
    seen: dict[str, Any] = {}

    def helper() -> None:
        seen["left"] = leave_the_loops_cpus()
        seen["after"] = os.sched_getaffinity(0)
        with on_the_loops_cpus(seen["left"]):
            seen["spawning"] = os.sched_getaffinity(0)
        seen["again"] = os.sched_getaffinity(0)

    def service_thread() -> None:
        os.sched_setaffinity(0, {loop_cpu})
        t = threading.Thread(target=helper)
        t.start()
        t.join()

    t = threading.Thread(target=service_thread)
    t.start()
    t.join()
    assert seen["left"] == {loop_cpu} == seen["spawning"]
    assert loop_cpu not in seen["after"] and seen["after"] and seen["again"] == seen["after"]
