"""A Zenoh client flooding the rig's ``rig/status`` queryable for the loop bench (its own
process, like a remote viewer gone wrong).

    python -m bench.zenoh_status_flood PORT [--rate 1000]

Connects to tcp/127.0.0.1:PORT (no scouting), prints ``connected`` once, then sends
status queries at ``--rate`` per second (not waiting for the replies) until SIGTERM and
prints ``queries N ok A``.  The rig answers a query over its rate limits with nothing
(it is counted there: ``status()["telemetry"]["status_refused"]``), so only the answers
call back into Python here: the client stands for another computer and should cost the
one it shares as little as it can.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import Any

import zenoh


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("port", type=int)
    ap.add_argument("--rate", type=float, default=1000.0)
    args = ap.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{args.port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    counts = {"ok": 0}
    lock = threading.Lock()

    def reply(r: Any) -> None:
        if r.ok is not None:
            with lock:
                counts["ok"] += 1

    with zenoh.open(c) as session:
        print("connected", flush=True)
        sent = 0
        t0 = time.monotonic()
        period = 1.0 / args.rate
        while not stop.is_set():
            session.get("rig/status", reply, timeout=2.0)
            sent += 1
            wait = t0 + sent * period - time.monotonic()
            if wait > 0:
                stop.wait(wait)
        time.sleep(0.5)
        print(f"queries {sent} ok {counts['ok']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
