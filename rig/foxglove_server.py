"""Live Foxglove view: a WebSocket server (the official foxglove-sdk) in the service.

The loop hands a packed tick record every ``cfg.rate_hz`` (:meth:`FoxgloveView.offer_tick`,
the same packing as the recording: :class:`rig.recording.codec.TickPacker`) and every
event (:meth:`FoxgloveView.offer_event`) to one bounded queue; a full queue drops the
item and counts it (:attr:`FoxgloveView.dropped`), so the loop never waits.  The
publisher thread decodes, splits and encodes the records exactly as the recording writer
does (``rig.recording.schema.split_record``, ``encode_json``) and logs them to the SDK,
whose own threads serve the clients: a slow client loses its oldest messages
(``cfg.client_backlog``) and cannot hold up the publisher, let alone the loop.

Channels (the recording's names and JSON Schemas, ``rig.recording.schema.TOPICS``):
``/rig/signals``, ``/controller/internals``, ``/rig/timing``, ``/rig/events``,
``/rig/log`` (foxglove.Log), ``/rig/scene`` (foxglove.SceneUpdate) and ``/tf``
(foxglove.FrameTransform).  The raw CAN frames are not served live.

A server that cannot start (port in use, address not on this computer) leaves the
view ``failed`` with a one-line :attr:`FoxgloveView.error`; the service goes on without
it.  Clients can only subscribe: the server advertises no client-publish, parameter or
service capability, so whatever a client sends is refused by the SDK (docs/foxglove.md).
What the SDK would log about it stays out of Python logging, and is escaped, capped and
rate-limited if forwarded all the same (``rig.sdk_logs``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import foxglove

from controller.config import FoxgloveConfig
from rig.recording.codec import TickDecoder, TickLayout, TickPacker
from rig.recording.scene import next_scene_ns, scene_json
from rig.recording.schema import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_LOG,
    TOPIC_SCENE,
    TOPIC_SIGNALS,
    TOPIC_TF,
    TOPIC_TIMING,
    TOPICS,
    encode_message,
    event_from_message,
    event_message,
    log_message,
    schema_bytes,
    split_record,
)
from rig.sdk_logs import install_filter, keep_sdk_logs_out

__all__ = ["LIVE_TOPICS", "SUBPROTOCOL", "FoxgloveView"]

#: the WebSocket subprotocol foxglove-sdk 0.30 serves (the messages of
#: foxglove.websocket.v1); a client that offers only the old name gets HTTP 400
SUBPROTOCOL = "foxglove.sdk.v1"

log = logging.getLogger(__name__)

#: the channels served live (names and schemas of the recording)
LIVE_TOPICS = (TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_TIMING, TOPIC_EVENTS, TOPIC_LOG,
               TOPIC_SCENE, TOPIC_TF)
_STOP = ("stop",)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


class FoxgloveView:
    """The live view of one service (see the module docstring).

    ``layout``: the loop's tick record layout; ``clock_offset_ns``: wall minus loop
    clock (messages carry wall time, like the recording's ``log_time``)."""

    def __init__(self, cfg: FoxgloveConfig, layout: TickLayout, *,
                 clock_offset_ns: int | None = None, name: str = "rig") -> None:
        self.cfg = cfg
        self.state = "starting"
        self.error: str | None = None
        self.dropped = 0          # items the loop could not queue
        self.published = 0        # messages logged to the SDK
        self.malformed = 0        # items the publisher could not encode
        self.port = cfg.port
        self._offset = (time.time_ns() - time.monotonic_ns() if clock_offset_ns is None
                        else clock_offset_ns)
        self._packer = TickPacker(layout)
        self._decoder = TickDecoder(layout)
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=cfg.queue_size)
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._channels: dict[str, foxglove.Channel] = {}
        keep_sdk_logs_out()                  # before the first server: rig.sdk_logs
        self._log_filter = install_filter()
        self._context = context = foxglove.Context()   # channels close with it
        try:
            self._server = foxglove.start_server(
                name=name, host=cfg.host, port=cfg.port, context=context,
                message_backlog_size=cfg.client_backlog)
        except Exception as exc:   # foxglove.FoxgloveError (RuntimeError): bind failed
            self.state = "failed"
            self.error = (f"foxglove view not started: cannot serve on "
                          f"{self._where(cfg.port)}: {_one_line(exc)}; control goes on "
                          "without it")
            log.error("%s", self.error)
            return
        self.port = int(self._server.port)
        for topic in LIVE_TOPICS:
            sch = TOPICS[topic]
            self._channels[topic] = foxglove.Channel(
                topic, message_encoding=MESSAGE_ENCODING, context=context,
                schema=foxglove.Schema(name=sch["title"], encoding=SCHEMA_ENCODING,
                                       data=schema_bytes(sch)))
        self._next_scene_ns: int | None = None
        self._thread = threading.Thread(target=self._run, name="foxglove-view", daemon=True)
        self.state = "serving"
        self._thread.start()
        log.info("foxglove view on ws://%s", self._where(self.port))

    def _where(self, port: int) -> str:
        host = self.cfg.host
        return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    @property
    def url(self) -> str:
        return f"ws://{self._where(self.port)}"

    # ------------------------------------------------------------------ loop side
    def offer_tick(self, t_ns: int, scalars: Any, arrays: Any) -> bool:
        """Queue one tick record (the recording's packing); False when dropped."""
        if self._thread is None:
            return False
        packer = self._packer
        packer.pack(t_ns, scalars, arrays)
        try:
            self._queue.put_nowait(("tick", bytes(packer.buffer)))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def offer_packed(self, item: bytes) -> bool:
        """Queue one tick record packed already (an ``ITEM_TICK`` of the layout, as the
        telemetry process gets it from the loop); False when dropped."""
        if self._thread is None:
            return False
        try:
            self._queue.put_nowait(("tick", item))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def set_layout(self, layout: TickLayout) -> None:
        """The tick records that follow have this layout (the publisher thread decodes
        each record with the decoder of the moment it takes it)."""
        self._packer = TickPacker(layout)
        self._decoder = TickDecoder(layout)

    def offer_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool:
        """Queue one event (lifecycle, fault, command, note); False when dropped."""
        if self._thread is None:
            return False
        try:
            self._queue.put_nowait(("event", t_ns, tick, kind, detail))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    # ------------------------------------------------------------------ publisher
    def _log(self, topic: str, payload: bytes, wall_ns: int) -> None:
        self._channels[topic].log(payload, log_time=wall_ns)
        self.published += 1

    def _publish_tick(self, item: bytes) -> None:
        channels = self._channels
        if not any(ch.has_sinks() for ch in channels.values()):
            return          # nobody subscribed: no decoding, no JSON (the thread idles)
        t_ns, record = self._decoder.decode(item)
        wall = max(t_ns + self._offset, 0)
        for topic, msg in split_record(t_ns, record):
            if channels[topic].has_sinks():
                self._log(topic, encode_message(msg), wall)
        if self._next_scene_ns is None or t_ns >= self._next_scene_ns:
            self._next_scene_ns = next_scene_ns(self._next_scene_ns, t_ns)
            if not (channels[TOPIC_TF].has_sinks() or channels[TOPIC_SCENE].has_sinks()):
                return
            tf, scene = scene_json(wall, record.get("rattlespace_m"),
                                   record.get("force_meas_n"),
                                   str(record.get("lifecycle", "")))
            self._log(TOPIC_TF, tf, wall)
            self._log(TOPIC_SCENE, scene, wall)

    def _publish_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> None:
        wall = max(t_ns + self._offset, 0)
        msg = event_message(t_ns, tick, kind, detail)
        self._log(TOPIC_EVENTS, encode_message(msg), wall)
        self._log(TOPIC_LOG, encode_message(log_message(wall, tick, msg["kind"],
                                                        event_from_message(msg)["detail"])),
                  wall)

    def _run(self) -> None:
        get = self._queue.get
        while True:
            item = get()
            if item is _STOP:
                return
            try:
                if item[0] == "tick":
                    self._publish_tick(item[1])
                else:
                    self._publish_event(*item[1:])
            except Exception as exc:   # never let one bad item end the view
                self.malformed += 1
                if self.malformed % 1000 == 1:
                    log.error("foxglove view: item not published (%d so far): %s",
                              self.malformed, _one_line(exc))

    # ------------------------------------------------------------------ outside
    def status(self) -> dict[str, Any]:
        return {"state": self.state, "url": self.url if self.state == "serving" else None,
                "host": self.cfg.host, "port": self.port, "error": self.error,
                "published": self.published, "dropped": self.dropped,
                "malformed": self.malformed, "rate_hz": self.cfg.rate_hz,
                "subprotocol": SUBPROTOCOL}

    def close(self) -> None:
        """Publish what is queued, stop the thread and the server (idempotent)."""
        thread, self._thread = self._thread, None
        if thread is not None:
            while True:
                try:
                    self._queue.put(_STOP, timeout=1.0)
                    break
                except queue.Full:
                    if not thread.is_alive():
                        break
            thread.join(timeout=5.0)
        if self._server is not None:
            server, self._server = self._server, None
            try:
                server.stop()
            except Exception as exc:
                log.warning("foxglove view: stopping the server: %s", _one_line(exc))
        self._log_filter.flush(log)
        if self.state == "serving":
            self.state = "stopped"

