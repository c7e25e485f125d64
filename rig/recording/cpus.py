"""Where the service's helpers run: off the loop's CPUs.

When the service process is pinned to some CPUs (systemd ``CPUAffinity=``) and others
exist, the loop's helpers leave them: the recording writer and the telemetry process
(child processes: ``stay_out_of_the_loops_way`` in :mod:`rig.recording.writer`) and the
loop process's own helper threads (the recorder's and the telemetry process's readers,
the status builder), so that the loop's CPU runs the loop and its caches keep the
loop's data between ticks.  "The loop's CPUs" are those a helper inherits at its start,
or, for a child process started from a helper thread that left them already (a
restarted telemetry process), those named in its environment (:data:`LOOP_CPUS_ENV`,
:func:`loop_cpus_env`): such a child starts, and imports its modules, off the loop's
CPUs while the loop runs.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

__all__ = ["LOOP_CPUS_ENV", "leave_the_loops_cpus", "loop_cpus_env"]

#: the environment variable naming the loop's CPUs to a child process ("1" or "2,3")
LOOP_CPUS_ENV = "RIG_LOOP_CPUS"


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


def _named_loop_cpus() -> set[int] | None:
    """The loop's CPUs named in this process's environment (:data:`LOOP_CPUS_ENV`), None
    when not named (or not readable)."""
    text = os.environ.get(LOOP_CPUS_ENV, "")
    try:
        cpus = {int(part) for part in text.split(",") if part.strip()}
    except ValueError:
        return None
    return cpus or None


def loop_cpus_env(cpus: set[int] | None) -> dict[str, str] | None:
    """The environment for a child process started off the loop's CPUs ``cpus`` (what
    :func:`leave_the_loops_cpus` returned): this process's, naming them, so that the
    child's :func:`leave_the_loops_cpus` knows them.  None (inherit the environment)
    when there is nothing to name."""
    if not cpus:
        return None
    return {**os.environ, LOOP_CPUS_ENV: ",".join(str(c) for c in sorted(cpus))}


def leave_the_loops_cpus() -> set[int] | None:
    """Move the calling thread off the loop's CPUs: those named in the environment
    (:data:`LOOP_CPUS_ENV`), else the CPUs it inherited, when the service is pinned to
    some (systemd ``CPUAffinity=``) and others exist.  Returns the loop's CPUs (a process
    this thread starts gets them with :func:`loop_cpus_env`), None when it stayed."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    with contextlib.suppress(OSError, ValueError):
        named = _named_loop_cpus()
        loop = os.sched_getaffinity(0) if named is None else named
        others = _online_cpus() - loop
        if others:
            os.sched_setaffinity(0, others)
            return loop
    return None
