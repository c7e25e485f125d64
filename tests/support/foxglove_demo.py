"""The rig demo with the live Foxglove view, and a client that connects to it once it is
up (tests/test_foxglove.py, tests/test_foxglove_logs.py)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from websockets.exceptions import InvalidHandshake
from websockets.sync.client import ClientConnection, connect

ROOT = Path(__file__).resolve().parents[2]
SUBPROTOCOL = "foxglove.websocket.v1"
#: foxglove-sdk 0.30 names the same protocol (same messages and opcodes) foxglove.sdk.v1
#: and refuses a handshake that offers only the old name; a client offers both
SUBPROTOCOLS = [SUBPROTOCOL, "foxglove.sdk.v1"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def demo(*args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "demo", "-q", "--json", "--no-telemetry",
         "--no-realtime", *args],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def connect_when_up(url: str, proc: subprocess.Popen[str], timeout_s: float = 90.0
                    ) -> ClientConnection:
    """The demo designs its bank before the server starts: retry until it answers."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            return connect(url, subprotocols=SUBPROTOCOLS,  # type: ignore[arg-type]
                           open_timeout=2.0)
        except (OSError, InvalidHandshake, TimeoutError):
            if proc.poll() is not None or time.monotonic() > end:
                raise
            time.sleep(0.2)


