"""The telemetry process: the Zenoh session and the live Foxglove server, fed by the loop.

Started by :class:`rig.telemetry_process.link.TelemetryLink` as ``python -m
rig.telemetry_process``; never run by hand.  It reads the feed on stdin
(:mod:`rig.telemetry_process.feed`: the recording's packed tick records, events, the
service's status, command replies), and

- hands every tick record and event to :class:`rig.foxglove_server.FoxgloveView`
  (decoding, JSON and the WebSocket clients all happen here);
- decodes a tick record every ``1 / telemetry.rate_hz`` (and right after a lifecycle or
  fault event) into the Zenoh snapshot (:func:`snapshot_of`) for
  :class:`rig.telemetry.TelemetryPublisher`, which answers ``rig/status`` queries from the
  last status the loop process sent;
- passes operator commands (validated by the publisher) to the loop process as JSON lines
  on stdout and waits up to :data:`COMMAND_TIMEOUT_S` for the reply on the feed.

Its own state (the Zenoh session's, the view's) goes to stdout as JSON lines every
second and at every change.  Whatever a client makes this process do, log or crash, the
loop's process only sees a slower feed (dropped and counted) or a lost process
(restarted).  SIGINT / SIGTERM are ignored: it ends when the feed ends.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import select
import struct
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any

from controller.config import parse_config, parse_toml
from rig.recording.codec import (
    ITEM_END,
    ITEM_EVENT,
    ITEM_HEAD,
    ITEM_LAYOUT,
    ITEM_TICK,
    TickDecoder,
    TickLayout,
    decode_item,
    read_stream_header,
    split_items,
)
from rig.recording.writer import ParentLines, stay_out_of_the_loops_way
from rig.telemetry_process.feed import (
    FEED_MAGIC,
    ITEM_REPLY,
    ITEM_STATUS,
    decode_reply,
    decode_status,
)

__all__ = ["COMMAND_TIMEOUT_S", "main", "snapshot_of"]

log = logging.getLogger(__name__)

#: how long a command waits for the loop's reply [s]
COMMAND_TIMEOUT_S = 2.0
#: the process's nice increment: on a busy computer (and where the loop has no real-time
#: policy) the network's work yields the CPU to the loop's process
NICE = 10
_STATE_EVERY_S = 1.0
_STATE_KEYS = ("rattlespace_m", "sprung_accel_mps2", "force_meas_n", "force_ref_n",
               "spool_cmd", "valve_enable", "sensor_counter", "firing_weight", "q", "models",
               "flags",
               "blending", "weight_set", "stop_contact_s", "stop_degraded",
               "sprung_mass_est_kg", "spring_rate_est_n_per_m", "damping_est_ns_per_m",
               "wheel_hop_hz", "tire_stiffness_est", "comfort_share", "ride_height_m")


def _finite_or_none(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def snapshot_of(t_ns: int, record: Mapping[str, Any], status: Mapping[str, Any]
                ) -> dict[str, Any]:
    """The Zenoh snapshot (docs/telemetry.md) of a decoded tick record; the fault's
    tick, detail and message and the run's timing summary come from the loop's last
    status (at most a status period old)."""
    fault = record.get("fault") or None
    timing = status.get("timing") if isinstance(status.get("timing"), Mapping) else {}
    assert isinstance(timing, Mapping)

    def us(key: str) -> Any:
        v = timing.get(key)
        return None if not isinstance(v, int | float) else _finite_or_none(v * 1e-6)

    return {
        "tick": record.get("tick"), "t_ns": t_ns,
        "lifecycle": record.get("lifecycle"),
        "fault": None if fault is None else {
            "code": fault, "tick": status.get("fault_tick"),
            "detail": status.get("fault_detail"), "message": status.get("fault_message")},
        "state": {k: record.get(k) for k in _STATE_KEYS},
        "timing": {"wake_late_s": record.get("wake_late_s"),
                   "compute_s": record.get("compute_s"),
                   "lateness_p99_s": us("lateness_p99_us"),
                   "max_lateness_s": us("lateness_max_us"),
                   "max_compute_s": us("step_max_us"),
                   "overruns": record.get("overruns_total"),
                   "misses": timing.get("misses"), "skipped": timing.get("skipped"),
                   "dropped_recording": record.get("dropped_recording"),
                   "dropped_feed": record.get("dropped_telemetry")},
    }


class _Commands:
    """Operator commands to the loop process and their replies back."""

    def __init__(self, out: ParentLines) -> None:
        self.out = out
        self.ids = itertools.count(1)
        self.lock = threading.Lock()
        self.waiting: dict[int, list[Any]] = {}   # id -> [Event, reply or None]

    def handle(self, name: str, args: dict[str, Any]) -> str:
        """TelemetryPublisher's command handler (a Zenoh thread; ``args`` validated)."""
        cid = next(self.ids)
        slot: list[Any] = [threading.Event(), None]
        with self.lock:
            self.waiting[cid] = slot
        try:
            if not self.out.send("command", id=cid, name=name, args=args):
                raise ValueError(f"{name}: the loop process is gone")
            if not slot[0].wait(COMMAND_TIMEOUT_S):
                raise ValueError(f"{name}: loop did not answer within {COMMAND_TIMEOUT_S} s")
        finally:
            with self.lock:
                self.waiting.pop(cid, None)
        accepted, message = slot[1]
        if not accepted:
            raise ValueError(message)
        return str(message)

    def reply(self, cid: int, accepted: bool, message: str) -> None:
        with self.lock:
            slot = self.waiting.get(cid)
        if slot is not None:
            slot[1] = (accepted, message)
            slot[0].set()


class _Process:
    """What the process holds: the publisher, the view and the loop's last status."""

    def __init__(self, header: Mapping[str, Any], out: ParentLines) -> None:
        self.out = out
        self.cfg = parse_config(parse_toml(str(header["config_toml"]), "<telemetry feed>"))
        self.layout = TickLayout.from_json(header["layout"])
        self.decoder = TickDecoder(self.layout)
        self.loop_status: dict[str, Any] = {"lifecycle": "STARTING"}
        self.commands = _Commands(out)
        self.view: Any = None
        self.tp: Any = None
        self.period_ns = int(1e9 / self.cfg.telemetry.rate_hz)
        self.next_due_ns: int | None = None
        self.publish_next = True
        self.malformed = 0
        if header.get("foxglove"):
            from rig.foxglove_server import FoxgloveView

            self.view = FoxgloveView(self.cfg.foxglove, self.layout,
                                     clock_offset_ns=int(header["clock_offset_ns"]),
                                     name=str(header.get("name", "rig")))
        if header.get("zenoh"):
            from rig.telemetry import TelemetryPublisher

            tcfg = self.cfg.telemetry
            self.tp = TelemetryPublisher(
                tcfg, self.status, self.commands.handle if tcfg.commands_enabled else None,
                on_state=lambda _state, _error: self.send_state())

    def status(self) -> dict[str, Any]:
        """The status a ``rig/status`` query gets: the loop's last, with the view's."""
        st = dict(self.loop_status)
        if self.view is not None:
            st["foxglove"] = self.view.status()
        return st

    def send_state(self, event: str = "state") -> None:
        self.out.send(event, telemetry=None if self.tp is None else self.tp.status(),
                      foxglove=None if self.view is None else self.view.status())

    def item(self, raw: memoryview) -> bool:
        """One feed item; False at the END item."""
        _size, kind = ITEM_HEAD.unpack_from(raw, 0)
        if kind == ITEM_TICK:
            self.tick(raw)
        elif kind == ITEM_EVENT:
            _, t_ns, tick, ev_kind, detail = decode_item(raw, None)
            if self.view is not None:
                self.view.offer_event(t_ns, tick, ev_kind, detail)
            if ev_kind in ("lifecycle", "fault"):
                self.publish_next = True
        elif kind == ITEM_STATUS:
            self.loop_status = decode_status(raw)
        elif kind == ITEM_REPLY:
            self.commands.reply(*decode_reply(raw))
        elif kind == ITEM_LAYOUT:
            layout = decode_item(raw, None)[1]
            if layout != self.layout:
                self.layout, self.decoder = layout, TickDecoder(layout)
                if self.view is not None:
                    self.view.set_layout(layout)
        elif kind == ITEM_END:
            return False
        else:
            raise ValueError(f"feed item kind {kind}")
        return True

    def tick(self, raw: memoryview) -> None:
        if self.view is not None:
            self.view.offer_packed(bytes(raw))
        if self.tp is None:
            return
        t_ns = struct.unpack_from("<q", raw, ITEM_HEAD.size)[0]
        if not (self.publish_next or self.next_due_ns is None or t_ns >= self.next_due_ns):
            return
        self.publish_next = False
        self.next_due_ns = t_ns + self.period_ns
        t_ns, record = self.decoder.decode(raw)
        self.tp.offer(snapshot_of(t_ns, record, self.loop_status))

    def close(self) -> None:
        if self.tp is not None:
            self.tp.close()
        if self.view is not None:
            self.view.close()


def main() -> int:
    stay_out_of_the_loops_way()
    with contextlib.suppress(OSError):
        os.nice(NICE)
    out = ParentLines(sys.stdout)
    fd = sys.stdin.fileno()
    try:
        header = read_stream_header(fd, FEED_MAGIC, "telemetry feed")
    except (OSError, ValueError, EOFError) as exc:
        print(f"rig.telemetry_process: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    logging.basicConfig(level=int(header.get("log_level", logging.INFO)),
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    proc = _Process(header, out)
    proc.send_state("ready")
    carry = b""
    last_state = time.monotonic()
    ended = False
    try:
        while not ended:
            ready, _, _ = select.select([fd], [], [], _STATE_EVERY_S)
            if ready:
                data = os.read(fd, 1 << 16)
                if not data:
                    break
                buf = carry + data if carry else data
                end, _count = split_items(buf)
                carry = buf[end:]
                mv = memoryview(buf)[:end]
                pos = 0
                while pos < end:
                    (size,) = struct.unpack_from("<I", mv, pos)
                    try:
                        if not proc.item(mv[pos:pos + size]):
                            ended = True
                            break
                    except Exception as exc:   # one bad item never ends the process
                        proc.malformed += 1
                        if proc.malformed % 1000 == 1:
                            log.error("telemetry process: item skipped (%d so far): %s",
                                      proc.malformed, f"{type(exc).__name__}: {exc}"[:200])
                    pos += size
            now = time.monotonic()
            if now - last_state >= _STATE_EVERY_S:
                last_state = now
                proc.send_state()
    except (OSError, ValueError) as exc:
        log.error("telemetry process: reading the feed: %s", exc)
    finally:
        proc.close()
        proc.send_state("final")     # the view "stopped", the session closed
    return 0
