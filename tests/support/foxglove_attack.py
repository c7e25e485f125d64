"""A live view attacked by a real WebSocket client on 127.0.0.1, in a process of its own
(the SDK takes its log level once per process).  ``python -m
tests.support.foxglove_attack`` prints one JSON object: every log record of the process
(name, level, text, whether ``rig.sdk_logs`` filtered it), the attack's duration and
whether the server still served a subscriber afterwards.

The attack: ``FLOOD`` invalid messages (``{``), ``FORGED`` ops whose names carry a
newline and a fake log line, one op name of 100 KB and one subscribe of ``UNKNOWN``
channel ids that do not exist."""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

FLOOD = 2000
FORGED = 20
UNKNOWN = 10_000
FAKE_LINE = "ERROR rig.service.lifecycle: ACTIVE -> FAULT (forged)"


class _Keep(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append({"name": record.name, "level": record.levelname,
                             "text": record.getMessage(),
                             "filtered": bool(getattr(record, "rig_sanitised", False))})


def _send_all(ws: Any, messages: list[str]) -> None:
    for m in messages:
        try:
            ws.send(m)
        except ConnectionClosed:
            return


def main() -> int:
    keep = _Keep()
    root = logging.getLogger()
    root.addHandler(keep)
    root.setLevel(logging.DEBUG)
    for noisy in ("websockets", "numba", "matplotlib"):
        logging.getLogger(noisy).setLevel(logging.WARNING)

    from controller.config import default_config
    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.foxglove_server import SUBPROTOCOL, FoxgloveView
    from rig.service.loop import tick_record_layout

    cfg = default_config().replace(foxglove={"enabled": True, "port": 0})
    rt = BankRuntime(cached_design(cfg), cfg=cfg)
    view = FoxgloveView(cfg.foxglove, tick_record_layout(rt))
    url = f"ws://127.0.0.1:{view.port}"
    attack = (["{"] * FLOOD
              + [json.dumps({"op": f"sub\n{FAKE_LINE}\n{i}"}) for i in range(FORGED)]
              + [json.dumps({"op": "x" * 100_000})]
              + [json.dumps({"op": "subscribe", "subscriptions": [
                  {"id": i, "channelId": 900_000 + i} for i in range(UNKNOWN)]})])
    t0 = time.monotonic()
    with connect(url, subprotocols=[SUBPROTOCOL], max_size=None,  # type: ignore[list-item]
                 open_timeout=10) as ws:
        _send_all(ws, attack)
        try:   # the SDK answers each in order: wait for the last one's status
            end = time.monotonic() + 60
            while time.monotonic() < end:
                if "unknown channel" in str(ws.recv(timeout=60)).lower():
                    break
        except (ConnectionClosed, TimeoutError):
            pass
    elapsed = time.monotonic() - t0
    with connect(url, subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:  # type: ignore[list-item]
        served = "serverInfo" in str(ws.recv(timeout=10))
    view.close()
    print(json.dumps({"records": keep.records, "elapsed_s": elapsed, "served": served,
                      "state": view.state}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
