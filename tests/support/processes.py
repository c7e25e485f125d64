"""Child processes of the tests: stop by SIGTERM, never leave one running."""

from __future__ import annotations

import contextlib
import signal
import subprocess
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
