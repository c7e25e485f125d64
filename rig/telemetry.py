"""Zenoh telemetry: decimated state out, status queryable, optional commands in.

The loop calls :meth:`TelemetryPublisher.offer` (usually when :meth:`due` says so); it
never blocks: a full queue drops the snapshot and counts it in :attr:`dropped`.  A
publisher thread opens the Zenoh session, encodes JSON and publishes under
``<key_prefix>/...``.  A session that cannot be opened is tried :data:`SESSION_ATTEMPTS`
times with growing pauses, every failure logged and shown in :meth:`status` (and via
``on_state`` to the service's systemd STATUS); then telemetry gives up while control
goes on.  The session connects only to the configured endpoints: gossip scouting and
autoconnect are off.  Key tree, snapshot layout, command semantics and the TLS /
access-control set-up for a rig network: ``docs/telemetry.md``.
"""

from __future__ import annotations

import json
import logging
import queue
import re
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from controller.config import TelemetryConfig
from rig.operator_commands import OPERATOR_COMMANDS, brief, validate_command
from rig.rate_limit import PeerBuckets, TokenBucket
from rig.recording.schema import encode_json

__all__ = ["MAX_ARGUMENT_BYTES", "MAX_ERROR_CHARS", "SESSION_ATTEMPTS", "TelemetryPublisher",
           "peer_of", "zenoh_config"]

log = logging.getLogger(__name__)

_PERIODIC_S = 1.0  # lifecycle / fault are re-published at least this often
_RETRY_MAX_S = 30.0  # longest pause between two attempts to open the session
#: attempts to open the session (pauses 1, 2, 4, 8 s: about 15 s) before giving up
SESSION_ATTEMPTS = 5
#: command arguments larger than this are refused unread
MAX_ARGUMENT_BYTES = 1024
#: error texts in command replies are cut to this length (never echo large input)
MAX_ERROR_CHARS = 200
#: status queries are answered from a status built on the publisher thread at most
#: this long ago [s] (a query never calls the status provider itself)
STATUS_REFRESH_S = 0.2
#: the error reply of a command query over the rate limit ([telemetry] commands_per_s);
#: a status query over its limit gets no reply at all (:meth:`TelemetryPublisher._on_status`)
_RATE_LIMITED_COMMAND = json.dumps({"accepted": False,
                                    "error": "rate limited: too many commands"})
_RUST_SOURCE = re.compile(r" at /\S+\.rs:\d+\.?")


def peer_of(source_info: Any, key_expr: object) -> str:
    """Who a query or put comes from, for the per-peer limits: the Zenoh id of its
    source when it names one (``source_info``, what the sender claims), else the key
    expression it used (a flood of one client uses one or a few)."""
    sid = getattr(source_info, "source_id", None) if source_info is not None else None
    if sid is not None:
        return _cap(f"zid:{sid}", 80)
    return _cap(f"key:{key_expr}", 80)


def _cap(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    return text if len(text) <= limit else f"{text[:limit - 3]}..."


def _zenoh_error(exc: BaseException) -> str:
    """One line of a Zenoh error without the Rust source locations."""
    text = _RUST_SOURCE.sub("", str(exc)).strip().replace("\n", " ")
    return _cap(text or type(exc).__name__, 300)


def zenoh_config(cfg: TelemetryConfig) -> zenoh.Config:
    """The session configuration: ``cfg.zenoh_config_file`` (if any) overridden by mode,
    endpoints (listen or connect) and multicast scouting from ``cfg``, with gossip
    scouting and every autoconnect off (whatever the file says): the session talks
    only to the configured endpoints and to who connects to them.

    When connecting, ``listen/endpoints`` is set empty (a Zenoh peer would otherwise
    listen on ``tcp/[::]:0``, i.e. every interface).  Raises ``ValueError`` naming the
    file or key when the configuration cannot be built."""
    if cfg.zenoh_config_file:
        try:
            conf = zenoh.Config.from_file(cfg.zenoh_config_file)
        except Exception as exc:   # zenoh.ZError: missing, unreadable, bad json5
            raise ValueError(f"zenoh_config_file {cfg.zenoh_config_file}: "
                             f"{_zenoh_error(exc)}") from exc
    else:
        conf = zenoh.Config()
    no_autoconnect: dict[str, list[str]] = {"router": [], "peer": []}
    for key, value in (
            ("mode", cfg.mode),
            ("listen/endpoints", cfg.endpoints if cfg.listen else []),
            ("connect/endpoints", [] if cfg.listen else cfg.endpoints),
            ("scouting/multicast/enabled", cfg.multicast_scouting),
            ("scouting/multicast/autoconnect", no_autoconnect),
            ("scouting/gossip/enabled", False),
            ("scouting/gossip/autoconnect", no_autoconnect)):
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:   # zenoh.ZError: e.g. an endpoint it cannot parse
            raise ValueError(f"zenoh {key} = {brief(value, 120)}: {_zenoh_error(exc)}"
                             ) from exc
    return conf


class TelemetryPublisher:
    """Publish loop snapshots over Zenoh from a thread of its own.

    ``status_provider()`` is called on the publisher thread every
    :data:`STATUS_REFRESH_S` (return a fresh dict of plain values); ``<prefix>/status``
    queries get its last result, encoded once (within ``[telemetry]``
    ``status_queries_per_s`` / ``status_burst`` and the per-peer limits; a query over
    them is counted and gets no reply).  ``command_handler(name, args) -> str`` is only
    wired when ``cfg.commands_enabled``; it runs on a Zenoh thread, must not block (queue
    the command for the loop) and raises ``ValueError`` to reject a command.
    ``on_state(state, error)`` is called on the publisher thread at every change of
    :attr:`state` (``connecting``, ``connected``, ``retrying``, ``failed``); it must not
    block either.
    """

    def __init__(self, cfg: TelemetryConfig, status_provider: Callable[[], Mapping[str, Any]],
                 command_handler: Callable[[str, dict[str, Any]], str] | None = None,
                 *, retry_s: float = 1.0, session_attempts: int = SESSION_ATTEMPTS,
                 on_state: Callable[[str, str | None], None] | None = None) -> None:
        if session_attempts < 1:
            raise ValueError(f"session_attempts {session_attempts}: must be >= 1")
        self.cfg = cfg
        self.session_attempts = session_attempts
        self._status_provider = status_provider
        self._command_handler = command_handler
        self._on_state = on_state
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
        # a query or put is let through by its peer's bucket (peer_of), then by the
        # bucket of all peers together: one peer flooding uses up its own share only
        self._status_reply: tuple[bool, bytes] | None = None   # (ok, JSON) for queries
        self._status_at = 0.0
        self._status_limit = TokenBucket(cfg.status_queries_per_s, cfg.status_burst)
        self._command_limit = TokenBucket(cfg.commands_per_s, cfg.command_burst)
        self._status_peers = PeerBuckets(cfg.status_queries_per_peer_s, cfg.status_peer_burst)
        self._command_peers = PeerBuckets(cfg.commands_per_peer_s, cfg.command_peer_burst)
        self.attempts = 0              # attempts to open the session so far
        self.state = "connecting"
        self.error: str | None = None  # why the session is not up (last failure)
        self._session: zenoh.Session | None = None
        self._connected = threading.Event()
        self._finished = threading.Event()   # connected, failed for good or closed
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
        when the queue is full or the publisher is closed or has failed."""
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

    @property
    def failed(self) -> bool:
        """True once telemetry has given up (the session could not be opened)."""
        return self.state == "failed"

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def wait_settled(self, timeout_s: float) -> bool:
        """Wait until the session is up or telemetry has given up; False on timeout."""
        return self._finished.wait(timeout_s)

    def status(self) -> dict[str, Any]:
        """State of the telemetry itself (plain values; any thread)."""
        status_peers, command_peers = self._status_peers.refused, self._command_peers.refused
        return {"state": self.state, "error": self.error, "attempts": self.attempts,
                "session_attempts": self.session_attempts,
                "endpoints": list(self.cfg.endpoints), "listen": self.cfg.listen,
                "published": self.published, "dropped": self.dropped,
                "commands_enabled": self.cfg.commands_enabled,
                "commands_received": self.commands_received,
                "status_refused": self._status_limit.refused + sum(status_peers.values()),
                "commands_refused": (self._command_limit.refused
                                     + sum(command_peers.values())),
                "status_refused_per_peer": _most(status_peers),
                "commands_refused_per_peer": _most(command_peers)}

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

    def _set_state(self, state: str, error: str | None) -> None:
        self.state, self.error = state, error
        if state in ("connected", "failed"):
            self._finished.set()
        if self._on_state is not None:
            try:
                self._on_state(state, error)
            except Exception:
                log.exception("telemetry state callback")

    def _open(self, conf: zenoh.Config) -> zenoh.Session:
        session = zenoh.open(conf)
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

    def _give_up(self, error: str) -> None:
        self._stop.set()          # offers are dropped and counted from now on
        log.error("telemetry off: %s; control goes on without it", error)
        self._set_state("failed", error)

    def _connect(self) -> bool:
        """Open the session (retrying); False when telemetry gave up or was closed."""
        try:
            conf = zenoh_config(self.cfg)
        except ValueError as exc:          # retrying cannot help
            self.attempts = 1
            self._give_up(str(exc))
            return False
        limit = self.session_attempts
        pause = self._retry_s
        while not self._stop.is_set():
            self.attempts += 1
            try:
                self._session = self._open(conf)
            except Exception as exc:       # zenoh.ZError: busy port, bad address, TLS...
                error = f"zenoh session: {_zenoh_error(exc)}"
                if self.attempts >= limit:
                    self._give_up(f"{error} ({self.attempts} of {limit} attempts)")
                    return False
                self._set_state("retrying", error)
                log.warning("telemetry: %s (attempt %d of %d, next in %.0f s)", error,
                            self.attempts, limit, pause)
                self._stop.wait(pause)
                pause = min(2.0 * pause, _RETRY_MAX_S)
                continue
            self._set_state("connected", None)
            log.info("telemetry: Zenoh session up (%s %s, key prefix %r)",
                     "listening on" if self.cfg.listen else "connecting to",
                     ", ".join(self.cfg.endpoints), self._prefix)
            self._refresh_status()
            self._connected.set()
            return True
        return False

    def _run(self) -> None:
        if not self._connect():
            self._finished.set()
            return
        while not self._stop.is_set():
            if time.monotonic() - self._status_at >= STATUS_REFRESH_S:
                self._refresh_status()
            try:
                snap = self._q.get(timeout=STATUS_REFRESH_S / 2)
            except queue.Empty:
                continue
            try:
                self._publish(snap)
                self.published += 1
            except Exception as exc:  # a bad snapshot must not kill telemetry
                self.error = f"publish: {type(exc).__name__}: {_cap(str(exc))}"
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
        # the provider's own telemetry entry (e.g. the telemetry process's) stays, the
        # session's state on top
        mine = status.get("telemetry")
        status["telemetry"] = {**(mine if isinstance(mine, dict) else {}), **self.status()}
        return status

    def _refresh_status(self) -> tuple[bool, bytes]:
        """Build the status reply now (the publisher thread, every STATUS_REFRESH_S):
        (ok, JSON bytes), kept for the queries until the next refresh."""
        try:
            reply = (True, encode_json(self._status()))
        except Exception as exc:
            reply = (False, json.dumps(
                {"error": _cap(f"status: {type(exc).__name__}: {exc}")}).encode())
        self._status_reply, self._status_at = reply, time.monotonic()
        return reply

    def _on_status(self, query: zenoh.Query) -> None:
        # Over the limit: counted (the buckets' ``refused``) and not answered: the query
        # ends at once with no reply.  A flood is mostly refusals, so a refusal does the
        # least there is: no reply to send (an error reply costs the process more than
        # the rest of the refused query's Python together, bench/README.md), no log
        # line, no status built or encoded.
        if not (self._status_peers.take(_query_peer(query)) and self._status_limit.take()):
            return
        # the reply goes out on the concrete key, whatever the query's key expression
        ok, body = self._status_reply or self._refresh_status()   # None: before the first
        if ok:
            query.reply(self._key("status"), body, encoding=zenoh.Encoding.APPLICATION_JSON)
        else:
            query.reply_err(body)

    def _command_name(self, key: str) -> str | None:
        """The command of a ``<prefix>/cmd/<name>`` key; None for a key expression with
        wildcards (a query such as ``rig/**`` is not a command and gets no reply)."""
        if "*" in key or "$" in key:
            return None
        return key[len(self._key("cmd/")):]

    def _handle(self, name: str, payload: bytes) -> tuple[bool, dict[str, Any]]:
        """Validate and run one command; (accepted, reply object).  Error texts are cut
        to :data:`MAX_ERROR_CHARS` and never repeat more than a few characters of the
        input."""
        with self._lock:
            self.commands_received += 1
        shown = name if name in OPERATOR_COMMANDS else brief(name)
        try:
            if len(payload) > MAX_ARGUMENT_BYTES:
                raise ValueError(f"command {shown}: arguments of {len(payload)} bytes, "
                                 f"at most {MAX_ARGUMENT_BYTES}")
            args = json.loads(payload) if payload.strip() else {}
            validate_command(name, args)
            assert self._command_handler is not None
            result = self._command_handler(name, args)
        except (ValueError, json.JSONDecodeError) as exc:
            return False, {"command": shown, "accepted": False, "error": _cap(str(exc))}
        except Exception as exc:
            return False, {"command": shown, "accepted": False,
                           "error": _cap(f"internal: {type(exc).__name__}: {exc}")}
        return True, {"command": name, "accepted": True, "result": _cap(str(result))}

    def _on_command_query(self, query: zenoh.Query) -> None:
        name = self._command_name(str(query.key_expr))
        if name is None:
            return
        if not (self._command_peers.take(_query_peer(query)) and self._command_limit.take()):
            query.reply_err(_RATE_LIMITED_COMMAND, encoding=zenoh.Encoding.APPLICATION_JSON)
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        ok, reply = self._handle(name, payload)
        if ok:
            query.reply(self._key(f"cmd/{name}"), json.dumps(reply),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        else:
            query.reply_err(json.dumps(reply), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _on_command_put(self, sample: zenoh.Sample) -> None:
        name = self._command_name(str(sample.key_expr))
        if name is None or not (
                self._command_peers.take(peer_of(sample.source_info, sample.key_expr))
                and self._command_limit.take()):
            return        # over the limit: dropped unread, no acknowledgement
        _, reply = self._handle(name, sample.payload.to_bytes())
        leaf = name if name in OPERATOR_COMMANDS else "invalid"
        if self._session is not None:
            self._session.put(self._key(f"ack/{leaf}"), json.dumps(reply),
                              encoding=zenoh.Encoding.APPLICATION_JSON)


def _query_peer(query: zenoh.Query) -> str:
    try:
        return peer_of(query.source_info, query.key_expr)
    except Exception:          # a query without the fields: one peer of its own
        return "key:?"


def _most(refused: Mapping[str, int], n: int = 8) -> dict[str, int]:
    """The ``n`` peers refused most (the status stays small however many peers)."""
    return dict(sorted(refused.items(), key=lambda kv: -kv[1])[:n])
