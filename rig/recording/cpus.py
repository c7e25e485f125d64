"""Where the service's helpers run: off the loop's CPUs.

When the service process is pinned to some CPUs (systemd ``CPUAffinity=``) and others
exist, the loop's helpers leave them: the recording writer and the telemetry process
(child processes: ``stay_out_of_the_loops_way`` in :mod:`rig.recording.writer`) and the
loop process's own helper threads (the recorder's and the telemetry process's readers,
the status builder), so that the loop's CPU runs the loop and its caches keep the
loop's data between ticks.  "The loop's CPUs" are those a helper inherits at its start.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["leave_the_loops_cpus", "on_the_loops_cpus"]


def _online_cpus() -> set[int]:
    try:
        text = Path("/sys/devices/system/cpu/online").read_text().strip()
    except OSError:
        return set(range(os.cpu_count() or 1))
    cpus: set[int] = set()
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        cpus.update(range(int(lo), int(hi or lo) + 1))
    return cpus


def leave_the_loops_cpus() -> set[int] | None:
    """Move the calling thread off the loop's CPUs: the CPUs it inherited when the
    service is pinned to some (systemd ``CPUAffinity=``) and others exist.  Returns the
    CPUs it left (the loop's; a process this thread starts should start there, so that
    it too finds the loop's CPUs and leaves them), None when it stayed."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    with contextlib.suppress(OSError, ValueError):
        inherited = os.sched_getaffinity(0)
        others = _online_cpus() - inherited
        if others:
            os.sched_setaffinity(0, others)
            return inherited
    return None


@contextlib.contextmanager
def on_the_loops_cpus(cpus: set[int] | None) -> Iterator[None]:
    """The calling thread back on ``cpus`` (what :func:`leave_the_loops_cpus` returned)
    for the block: a process it starts there inherits the loop's CPUs and so finds the
    others to move to.  None: nothing to do."""
    if not cpus:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, cpus)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, before)
