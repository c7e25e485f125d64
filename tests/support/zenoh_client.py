"""A Zenoh client of the rig's telemetry on 127.0.0.1 (no scouting): session, queries."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable
from typing import Any

import zenoh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client_session(port: int) -> zenoh.Session:
    """A second, independent session connecting to the rig's (no listener)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def query(session: zenoh.Session, key: str, payload: str | None = None,
          timeout_s: float = 3.0) -> list[tuple[bool, dict[str, Any]]]:
    """The replies to one query: (ok, JSON body) each."""
    out = []
    for r in session.get(key, payload=payload, timeout=timeout_s):
        answer = r.ok if r.ok is not None else r.err
        assert answer is not None
        out.append((r.ok is not None, json.loads(answer.payload.to_bytes())))
    return out


def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return pred()
