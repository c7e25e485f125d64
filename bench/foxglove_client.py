"""A Foxglove WebSocket client for the loop bench (its own process, like a remote viewer).

    python -m bench.foxglove_client PORT [--stalled | --flood]

Connects to ws://127.0.0.1:PORT, subscribes to every advertised channel, prints
``subscribed N`` once, then reads messages until SIGTERM and prints ``messages M``.
``--stalled`` subscribes and never reads again: a viewer that hangs (the server's
per-client backlog fills and drops; the loop must not notice).  ``--flood`` subscribes,
then sends what the SDK refuses as fast as it can: ``{`` (invalid JSON), op names with a
newline and a forged log line, and now and then a subscribe of 10,000 unknown channel
ids (the probe of issue 25); it reads nothing.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("port", type=int)
    ap.add_argument("--stalled", action="store_true")
    ap.add_argument("--flood", action="store_true")
    args = ap.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with connect(f"ws://127.0.0.1:{args.port}",
                 subprotocols=SUBPROTOCOLS) as ws:  # type: ignore[arg-type]
        channels: dict[int, str] = {}
        end = time.monotonic() + 10.0
        while len(channels) < 4 and time.monotonic() < end:
            msg = ws.recv(timeout=5)
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") == "advertise":
                    channels.update({c["id"]: c["topic"] for c in m["channels"]})
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": cid} for i, cid in enumerate(channels)]}))
        print(f"subscribed {len(channels)}", flush=True)
        n = 0
        unknown = json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 1000 + i, "channelId": 900_000 + i} for i in range(10_000)]})
        forged = json.dumps({"op": "sub\nERROR rig.service.lifecycle: ACTIVE -> FAULT "
                                   "(forged)\n"})
        while not stop.is_set():
            if args.flood:
                try:
                    for _ in range(200):
                        ws.send("{")
                    ws.send(forged)
                    n += 201
                    if n % 20_100 == 0:
                        ws.send(unknown)
                except ConnectionClosed:
                    break
                continue
            if args.stalled:
                stop.wait(0.5)
                continue
            try:
                ws.recv(timeout=0.5)
                n += 1
            except TimeoutError:
                continue
            except ConnectionClosed:
                break
        print(f"messages {n}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
