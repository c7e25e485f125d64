"""A separate telemetry consumer process: subscribes to ``<prefix>/**`` over Zenoh.

    python -m tests.socketcan.zenoh_listener --connect tcp/127.0.0.1:PORT --out samples.jsonl

Peer mode, connect-only (nothing listens), multicast scouting off; connecting is retried
until the service is up.  Every sample is appended to ``--out`` as one JSON line
``{"key": ..., "t_rx_s": <host monotonic>, "payload": <decoded JSON or text>}``.
Prints ``listener subscribed`` once the subscriber is declared; stops on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh


def session_config(endpoint: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("connect/retry", '{"period_init_ms": 100, "period_max_ms": 500, '
                                       '"period_increase_factor": 1.5}')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


class Operator:
    """The operator's side of the service's Zenoh interface (commands and status), as a
    separate session in the test process."""

    def __init__(self, endpoint: str, prefix: str = "rig") -> None:
        self.prefix = prefix
        self.session = zenoh.open(session_config(endpoint))

    def close(self) -> None:
        self.session.close()

    def _get(self, key: str, payload: str | None, timeout_s: float) -> dict[str, Any] | None:
        kwargs: dict[str, Any] = {"timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = payload
        for reply in self.session.get(f"{self.prefix}/{key}", **kwargs):
            if reply.ok is not None:
                return dict(json.loads(reply.ok.payload.to_bytes()))
            if reply.err is not None:
                return {"accepted": False, "error": reply.err.payload.to_string()}
        return None

    def status(self, timeout_s: float = 5.0) -> dict[str, Any] | None:
        return self._get("status", None, timeout_s)

    def command(self, name: str, args: dict[str, Any] | None = None,
                timeout_s: float = 5.0) -> dict[str, Any] | None:
        return self._get(f"cmd/{name}", json.dumps(args or {}), timeout_s)

    def recover(self, state: Callable[[], tuple[str | None, str | None]],
                timeout_s: float) -> bool:
        """Reset (while FAULT) and arm (while INACTIVE) until ``state()`` says ACTIVE for
        0.5 s (a reset can be accepted in a tick where a slow periodic condition, e.g.
        RigStatus supply loss at 100 Hz, is not visible, and the fault latches again)."""
        deadline = time.monotonic() + timeout_s
        active_since: float | None = None
        while time.monotonic() < deadline:
            lifecycle, _ = state()
            if lifecycle == "ACTIVE":
                active_since = active_since or time.monotonic()
                if time.monotonic() - active_since >= 0.5:
                    return True
            else:
                active_since = None
                if lifecycle == "FAULT":
                    self.command("reset", timeout_s=2.0)
                elif lifecycle == "INACTIVE":
                    self.command("arm", timeout_s=2.0)
            time.sleep(0.2)
        return False


class TelemetryState:
    """The service's lifecycle and fault as the listener process received them (read
    from its output file: polling the service's status queryable instead would load
    the service's interpreter, whose loop thread competes for the GIL)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._offset = 0
        self._partial = ""
        self.lifecycle: str | None = None
        self.fault: str | None = None

    def __call__(self) -> tuple[str | None, str | None]:
        if self.path.exists():
            with open(self.path) as fh:
                fh.seek(self._offset)
                chunk = fh.read()
                self._offset = fh.tell()
            lines = (self._partial + chunk).split("\n")
            self._partial = lines.pop()
            for line in lines:
                with contextlib.suppress(ValueError):
                    sample = json.loads(line)
                    payload = sample.get("payload") or {}
                    if sample["key"].endswith("/lifecycle"):
                        self.lifecycle = payload.get("lifecycle")
                    elif sample["key"].endswith("/fault"):
                        f = payload.get("fault")
                        self.fault = f.get("code") if isinstance(f, dict) else None
        return self.lifecycle, self.fault

    def wait_for(self, lifecycle: str, timeout_s: float) -> tuple[str | None, str | None]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = self()
            if state[0] == lifecycle and (lifecycle != "FAULT" or state[1] is not None):
                return state
            time.sleep(0.1)
        return self()


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True, help="e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--prefix", default="rig")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    lock = threading.Lock()
    count = 0
    with open(args.out, "w") as out, zenoh.open(session_config(args.connect)) as session:

        def on_sample(sample: zenoh.Sample) -> None:
            nonlocal count
            raw = sample.payload.to_bytes()
            payload: Any
            try:
                payload = json.loads(raw)
            except ValueError:
                payload = raw.decode(errors="replace")
            line = json.dumps({"key": str(sample.key_expr), "t_rx_s": time.monotonic(),
                               "payload": payload})
            with lock:
                out.write(line + "\n")
                out.flush()
                count += 1

        sub = session.declare_subscriber(f"{args.prefix}/**", on_sample)
        print("listener subscribed", flush=True)
        stop.wait()
        sub.undeclare()
    print(f"listener samples={count}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
