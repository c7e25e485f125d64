"""Child processes of the tests: stop by SIGTERM, never leave one running."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterator


def sigterm_and_wait(proc: subprocess.Popen[str], timeout_s: float) -> tuple[str, str]:
    """Send SIGTERM, wait up to ``timeout_s`` for the process to end, return its
    (stdout, stderr); kill it (by its own handle) if it is still running after that."""
    with killed_on_exit(proc):
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=timeout_s)
    return out or "", err or ""


@contextlib.contextmanager
def killed_on_exit(proc: subprocess.Popen[str]) -> Iterator[subprocess.Popen[str]]:
    """The block's child process, killed (by its own handle) if the block leaves it running
    (an assertion before the test stopped it)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def stop_and_wait_stopped(pid: int, timeout_s: float = 30.0) -> None:
    """SIGSTOP the test's own child ``pid`` and wait until the kernel shows it stopped
    (state T in /proc/PID/task/*/stat, every thread).  kill() only queues the signal: a
    child blocked in a read completes that read first, so a test that wrote to it at
    once could still see it take data after the kill."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(state in ("T", "t") for state in _thread_states(pid)):
            return
        time.sleep(0.001)
    raise TimeoutError(f"process {pid} not stopped {timeout_s:g} s after SIGSTOP")


def _thread_states(pid: int) -> list[str]:
    """The state letter of every thread of ``pid`` (/proc/PID/task/TID/stat).  The
    process's own stat shows its main thread only: a group stop reaches the threads one
    by one, and a reader thread can still take data after the main thread shows T."""
    states = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat", encoding="ascii") as f:
                states.append(f.read().rsplit(")", 1)[1].split()[0])
        except FileNotFoundError:       # the thread ended meanwhile
            continue
    return states
