"""Zenoh telemetry: decimated state out, status queryable, optional commands in.

The loop calls :meth:`TelemetryPublisher.offer` (usually when :meth:`due` says so); it
never blocks: a full queue drops the snapshot and counts it in :attr:`dropped`.  A
publisher thread opens the Zenoh session (retrying while the network is down), encodes
JSON and publishes under ``<key_prefix>/...``.  Key tree, snapshot layout, command
semantics and the TLS / access-control set-up for a rig network: ``docs/telemetry.md``.
"""

from __future__ import annotations

import json
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from controller.config import TelemetryConfig
from rig.mcap_schema import encode_json

__all__ = ["COMMANDS", "TelemetryPublisher", "validate_command", "zenoh_config"]

#: command -> {argument: accepted types}; no other arguments are accepted.
COMMANDS: dict[str, dict[str, tuple[type, ...]]] = {
    "arm": {},
    "disarm": {},
    "reset": {},
    "weight_set": {"weight_set": (int,)},
    "blending": {"blending": (str, int)},
    "road": {"speed_mps": (int, float), "roughness_gd": (int, float)},
}
_PERIODIC_S = 1.0  # lifecycle / fault are re-published at least this often


def zenoh_config(cfg: TelemetryConfig) -> zenoh.Config:
    """The session configuration: ``cfg.zenoh_config_file`` (if any) overridden by mode,
    endpoints (listen or connect) and multicast scouting from ``cfg``.

    When connecting, ``listen/endpoints`` is set empty (a Zenoh peer would otherwise
    listen on ``tcp/[::]:0``, i.e. every interface)."""
    conf = zenoh.Config.from_file(cfg.zenoh_config_file) if cfg.zenoh_config_file \
        else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("listen/endpoints", json.dumps(cfg.endpoints if cfg.listen else []))
    conf.insert_json5("connect/endpoints", json.dumps([] if cfg.listen else cfg.endpoints))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    return conf


def validate_command(name: str, args: object) -> dict[str, Any]:
    """Check a command name and its argument object; ValueError names what is wrong."""
    if name not in COMMANDS:
        raise ValueError(f"unknown command {name!r}: allowed {', '.join(COMMANDS)}")
    if not isinstance(args, dict):
        raise ValueError(f"command {name!r}: arguments must be a JSON object, got {args!r}")
    spec = COMMANDS[name]
    extra = set(args) - set(spec)
    if extra:
        raise ValueError(f"command {name!r}: unknown argument(s) {sorted(extra)}; "
                         f"allowed {sorted(spec) or 'none'}")
    for key, types in spec.items():
        if key not in args:
            raise ValueError(f"command {name!r}: missing argument {key!r}")
        v = args[key]
        if isinstance(v, bool) or not isinstance(v, types):
            raise ValueError(f"command {name!r}: {key}={v!r} must be "
                             f"{' or '.join(t.__name__ for t in types)}")
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"command {name!r}: {key}={v!r} must be finite")
    return args


class TelemetryPublisher:
    """Publish loop snapshots over Zenoh from a thread of its own.

    ``status_provider()`` answers ``<prefix>/status`` queries (called on a Zenoh thread:
    return a fresh dict of plain values).  ``command_handler(name, args) -> str`` is only
    wired when ``cfg.commands_enabled``; it runs on a Zenoh thread, must not block (queue
    the command for the loop) and raises ``ValueError`` to reject a command.
    """

    def __init__(self, cfg: TelemetryConfig, status_provider: Callable[[], Mapping[str, Any]],
                 command_handler: Callable[[str, dict[str, Any]], str] | None = None,
                 *, retry_s: float = 1.0) -> None:
        self.cfg = cfg
        self._status_provider = status_provider
        self._command_handler = command_handler
        self._retry_s = retry_s
        self._prefix = cfg.key_prefix.rstrip("/")
        self._q: queue.Queue[Mapping[str, Any]] = queue.Queue(maxsize=cfg.queue_size)
        self._period_ns = int(1e9 / cfg.rate_hz)
        self._last_due_ns: int | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.dropped = 0
        self.published = 0
        self.commands_received = 0
        self.error: str | None = None
        self._session: zenoh.Session | None = None
        self._connected = threading.Event()
        self._declared: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._last_lifecycle: tuple[Any, float] = (object(), 0.0)
        self._last_fault: tuple[Any, float] = (object(), 0.0)
        self._thread = threading.Thread(target=self._run, name="rig-telemetry", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ loop side

    def due(self, t_ns: int) -> bool:
        """True at most every 1/rate_hz (loop clock ``t_ns``): time to build a snapshot."""
        if self._last_due_ns is None or t_ns - self._last_due_ns >= self._period_ns:
            self._last_due_ns = t_ns
            return True
        return False

    def offer(self, snapshot: Mapping[str, Any]) -> bool:
        """Queue a snapshot for publishing.  Never blocks; False (and ``dropped`` += 1)
        when the queue is full or the publisher is closed."""
        if self._stop.is_set():
            self.dropped += 1
            return False
        try:
            self._q.put_nowait(snapshot)
        except queue.Full:
            self.dropped += 1
            return False
        return True

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def close(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)

    def __enter__(self) -> TelemetryPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ thread

    def _key(self, leaf: str) -> str:
        return f"{self._prefix}/{leaf}"

    def _open(self) -> zenoh.Session:
        session = zenoh.open(zenoh_config(self.cfg))
        try:
            self._declare(session)
        except Exception:
            self._declared.clear()
            self._pubs.clear()
            session.close()
            raise
        return session

    def _declare(self, session: zenoh.Session) -> None:
        enc = zenoh.Encoding.APPLICATION_JSON
        for leaf in ("state", "timing", "lifecycle", "fault"):
            self._pubs[leaf] = session.declare_publisher(
                self._key(leaf), encoding=enc, congestion_control=zenoh.CongestionControl.DROP)
        self._declared.append(session.declare_queryable(self._key("status"), self._on_status))
        if self.cfg.commands_enabled and self._command_handler is not None:
            self._declared.append(
                session.declare_queryable(self._key("cmd/**"), self._on_command_query))
            self._declared.append(
                session.declare_subscriber(self._key("cmd/**"), self._on_command_put))

    def _run(self) -> None:
        while not self._stop.is_set() and self._session is None:
            try:
                self._session = self._open()
                self.error = None
                self._connected.set()
            except Exception as exc:  # zenoh.ZError, bad config file...: keep retrying
                self.error = f"zenoh session: {exc}"
                self._stop.wait(self._retry_s)
        while not self._stop.is_set():
            try:
                snap = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self._publish(snap)
                self.published += 1
            except Exception as exc:  # a bad snapshot must not kill telemetry
                self.error = f"publish: {type(exc).__name__}: {exc}"
        if self._session is not None:
            for d in self._declared:
                d.undeclare()
            self._session.close()

    def _publish(self, snap: Mapping[str, Any]) -> None:
        head = {"tick": snap.get("tick"), "t_ns": snap.get("t_ns")}
        state = snap.get("state")
        if state is not None:
            self._pubs["state"].put(encode_json({**head, **state}))
        timing = dict(snap.get("timing") or {})
        timing["dropped_telemetry"] = self.dropped
        self._pubs["timing"].put(encode_json({**head, **timing}))
        now = time.monotonic()
        for leaf, key, attr in (("lifecycle", "lifecycle", "_last_lifecycle"),
                                ("fault", "fault", "_last_fault")):
            if key not in snap:
                continue
            value = snap[key]
            last, when = getattr(self, attr)
            if value != last or now - when >= _PERIODIC_S:
                self._pubs[leaf].put(encode_json({**head, key: value}))
                setattr(self, attr, (value, now))

    # ------------------------------------------------------------------ zenoh callbacks

    def _status(self) -> dict[str, Any]:
        status = dict(self._status_provider())
        status["telemetry"] = {"dropped": self.dropped, "published": self.published,
                               "commands_enabled": self.cfg.commands_enabled,
                               "error": self.error}
        return status

    def _on_status(self, query: zenoh.Query) -> None:
        try:
            query.reply(query.key_expr, encode_json(self._status()),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as exc:
            query.reply_err(json.dumps({"error": f"status: {type(exc).__name__}: {exc}"}))

    def _handle(self, key: str, payload: bytes) -> tuple[bool, dict[str, Any]]:
        """Validate and run one command; (accepted, reply object)."""
        with self._lock:
            self.commands_received += 1
        name = key[len(self._key("cmd/")):]
        try:
            args = json.loads(payload) if payload.strip() else {}
            validate_command(name, args)
            assert self._command_handler is not None
            result = self._command_handler(name, args)
        except (ValueError, json.JSONDecodeError) as exc:
            return False, {"command": name, "accepted": False, "error": str(exc)}
        except Exception as exc:
            return False, {"command": name, "accepted": False,
                           "error": f"internal: {type(exc).__name__}: {exc}"}
        return True, {"command": name, "accepted": True, "result": str(result)}

    def _on_command_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        ok, reply = self._handle(str(query.key_expr), payload)
        if ok:
            query.reply(query.key_expr, json.dumps(reply),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        else:
            query.reply_err(json.dumps(reply), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_command_put(self, sample: zenoh.Sample) -> None:
        _, reply = self._handle(str(sample.key_expr), sample.payload.to_bytes())
        if self._session is not None:
            self._session.put(self._key(f"ack/{reply['command']}"), json.dumps(reply),
                              encoding=zenoh.Encoding.APPLICATION_JSON)
