"""MCAP run recording: raw CAN frames, tick records and events, written off the loop thread.

The 1 kHz loop calls :meth:`RunRecorder.can_frame`, :meth:`RunRecorder.tick` and
:meth:`RunRecorder.event`; each only appends a plain tuple to a bounded deque (no JSON,
no I/O, no lock) and returns ``False`` (counting :attr:`RunRecorder.dropped`) when the
queue is full or the writer has failed.  A writer thread encodes JSON, fills MCAP chunks
(``cfg.chunk_bytes``), flushes every finished chunk to the OS (so a SIGKILL loses at most
the open chunk) and rotates into numbered files (``rotate_bytes`` / ``rotate_seconds``).

Format, channels and the tick-record keys: ``docs/recording.md``.  :func:`read_run`
reads a run back (tolerating a missing footer / truncated tail) for replay and report.
"""

from __future__ import annotations

import collections
import hashlib
import json
import platform
import threading
import time
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import IO, Any

from mcap.records import Attachment, Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from controller.config import RecordingConfig
from rig.mcap_schema import (
    EVENT_KINDS,
    MESSAGE_ENCODING,
    RECORDING_FORMAT_VERSION,
    SCHEMA_ENCODING,
    SIGNAL_KEYS,
    TIMING_KEYS,
    TOPIC_CAN_RX,
    TOPIC_CAN_TX,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_SIGNALS,
    TOPIC_TIMING,
    TOPICS,
    encode_json,
    schema_bytes,
)

__all__ = [
    "CanFrameRecord",
    "EventRecord",
    "RunData",
    "RunRecorder",
    "TickRecord",
    "read_run",
    "segment_paths",
]

CONFIG_ATTACHMENT = "config.toml"
DESIGN_ATTACHMENT = "design.npz"
METADATA_NAME = "rig"
_RECORD_TOPICS = (TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_TIMING)
PARTS_KEY = "record_parts"  # in /rig/signals: how many messages the tick record has
_RESERVED = frozenset({"tick", "t_ns", PARTS_KEY})
_FRAME, _TICK, _EVENT = 0, 1, 2
_EVENT_HEADROOM = 1024  # events may exceed queue_size by this much (they are rare)


def _segment_path(base: Path, index: int) -> Path:
    return base if index == 0 else base.with_name(f"{base.stem}.{index:03d}.mcap")


def segment_paths(base: str | Path) -> list[Path]:
    """``base`` and its existing rotation successors ``<stem>.001.mcap``, ... in order."""
    base = Path(base)
    paths = [base]
    while (nxt := _segment_path(base, len(paths))).exists():
        paths.append(nxt)
    return paths


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("lqg-fuzzy-rig", "numpy", "mcap", "eclipse-zenoh", "python-can", "numba"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def _config_hash(config_toml: str) -> str:
    """controller.config.config_hash of the TOML (as the design artifact stores it)."""
    from controller.config import config_hash, parse_config

    try:
        return config_hash(parse_config(tomllib.loads(config_toml)))
    except Exception as exc:  # recorded, never fatal: the raw TOML is attached anyway
        return f"unparseable: {exc}"


class RunRecorder:
    """Record one run into ``path_or_dir`` (a ``.mcap`` file, or a directory that gets
    ``run-<UTC>.mcap``).  Rotation continues in ``<stem>.001.mcap``, ``.002`` ...

    ``t_ns`` arguments must all come from one clock (the loop's; ``clock`` names it for
    the metadata).  MCAP ``log_time`` = ``t_ns + clock_offset_ns`` (default: wall minus
    monotonic at start, so tools show wall time); payloads keep the raw ``t_ns``.
    """

    def __init__(self, path_or_dir: str | Path, cfg: RecordingConfig, *, config_toml: str,
                 design_bytes: bytes | None, metadata: Mapping[str, Any],
                 clock: str = "monotonic", clock_offset_ns: int | None = None,
                 compression: str = "zstd", poll_s: float = 0.002,
                 max_chunk_age_s: float = 1.0) -> None:
        target = Path(path_or_dir)
        if target.suffix != ".mcap":
            stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
            target = target / f"run-{stamp}.mcap"
        target.parent.mkdir(parents=True, exist_ok=True)
        if compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"compression {compression!r}: allowed zstd, lz4, none")
        self.base_path = target
        self.paths: list[Path] = []
        self._cfg = cfg
        self._compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                             "none": CompressionType.NONE}[compression]
        self._config_toml = config_toml
        self._design = design_bytes
        if clock_offset_ns is None:
            clock_offset_ns = time.time_ns() - time.monotonic_ns() if clock == "monotonic" else 0
        self._offset = int(clock_offset_ns)
        self._meta = self._base_metadata(metadata, clock)
        self._poll_s = poll_s
        self._max_chunk_age_s = max_chunk_age_s
        self._rotate_ns = int(cfg.rotate_seconds * 1e9)

        self._q: collections.deque[tuple[Any, ...]] = collections.deque()
        self._limit = cfg.queue_size
        self._dropped = 0
        self._closing = False
        self._closed = False
        self._failed = False
        self.error: str | None = None
        self.malformed = 0           # items the writer could not encode (skipped)
        self.last_malformed: str | None = None
        self.written = 0             # items written (frames + records + events)
        self._seq = 0

        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._seg_t0: int | None = None
        self._open_segment()         # errors (permissions, disk) raise here, not later
        self._thread = threading.Thread(target=self._run, name="rig-recorder", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ loop side (cheap)

    @property
    def dropped(self) -> int:
        """Items not recorded because the queue was full, the writer failed or closed."""
        return self._dropped

    def can_frame(self, t_ns: int, tick: int, arbitration_id: int, data: bytes | bytearray,
                  is_rx: bool) -> bool:
        """Queue one raw frame (``data`` is copied).  Never blocks; False = dropped."""
        if len(self._q) >= self._limit or self._failed or self._closing:
            self._dropped += 1
            return False
        self._q.append((_FRAME, t_ns, tick, arbitration_id, bytes(data), is_rx))
        return True

    def tick(self, t_ns: int, record: Mapping[str, Any]) -> bool:
        """Queue one tick record (flat dict with ``tick``; keys: docs/recording.md).

        The dict and its values are kept by reference: hand over a fresh dict each tick
        and copies of arrays that the runtime updates in place."""
        if len(self._q) >= self._limit or self._failed or self._closing:
            self._dropped += 1
            return False
        self._q.append((_TICK, t_ns, record))
        return True

    def event(self, t_ns: int, tick: int, kind: str, detail: Mapping[str, Any] | str | None
              ) -> bool:
        """Queue a lifecycle / command / fault / note event (may use a little headroom
        beyond ``queue_size`` so rare events survive a frame flood)."""
        if len(self._q) >= self._limit + _EVENT_HEADROOM or self._failed or self._closing:
            self._dropped += 1
            return False
        self._q.append((_EVENT, t_ns, tick, kind, detail))
        return True

    def close(self, timeout_s: float = 30.0) -> None:
        """Drain the queue, write the summary and footer, close the file.  Idempotent."""
        if self._closed:
            return
        self._closing = True
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            self.error = self.error or f"writer did not drain within {timeout_s} s"
            self._failed = True
            self._thread.join(5.0)
        self._closed = True
        if not self._thread.is_alive():
            try:
                self._finish_segment()
            except OSError as exc:
                self.error = self.error or f"closing {self.paths[-1]}: {exc}"

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writer thread

    def _base_metadata(self, user: Mapping[str, Any], clock: str) -> dict[str, str]:
        meta = {
            "format_version": str(RECORDING_FORMAT_VERSION),
            "run_id": self.base_path.stem,
            "created_utc": datetime.now(UTC).isoformat(),
            "clock": clock,
            "clock_offset_ns": str(self._offset),
            "config_hash": _config_hash(self._config_toml),
            "config_toml_sha256": hashlib.sha256(self._config_toml.encode()).hexdigest(),
            "design_sha256": (hashlib.sha256(self._design).hexdigest()
                              if self._design is not None else ""),
            "versions": json.dumps(_versions(), sort_keys=True),
        }
        for k, v in user.items():
            meta[str(k)] = v if isinstance(v, str) else json.dumps(v, default=str)
        return meta

    def _open_segment(self) -> None:
        path = _segment_path(self.base_path, len(self.paths))
        stream = open(path, "wb")  # noqa: SIM115 (closed in _finish_segment)
        writer = Writer(stream, chunk_size=self._cfg.chunk_bytes,
                        compression=self._compression)
        writer.start(profile="", library=f"rig-recorder/{RECORDING_FORMAT_VERSION}")
        now = time.time_ns()
        writer.add_metadata(METADATA_NAME, {**self._meta, "segment": str(len(self.paths))})
        writer.add_attachment(now, now, CONFIG_ATTACHMENT, "application/toml",
                              self._config_toml.encode())
        if self._design is not None:
            writer.add_attachment(now, now, DESIGN_ATTACHMENT, "application/octet-stream",
                                  self._design)
        self._channels = {}
        for topic, schema in TOPICS.items():
            sid = writer.register_schema(schema["title"], SCHEMA_ENCODING,
                                         schema_bytes(schema))
            self._channels[topic] = writer.register_channel(topic, MESSAGE_ENCODING, sid)
        stream.flush()
        self.paths.append(path)
        self._stream, self._writer = stream, writer
        self._seg_t0 = None
        self._last_size = stream.tell()
        self._last_chunk_mono = time.monotonic()

    def _finish_segment(self) -> None:
        if self._writer is not None and self._stream is not None:
            self._writer.finish()
            self._stream.close()
        self._writer = self._stream = None

    def _maybe_rotate(self, t_ns: int, check_size: bool) -> None:
        if self._seg_t0 is None:
            self._seg_t0 = t_ns
            return
        assert self._stream is not None
        if (t_ns - self._seg_t0 >= self._rotate_ns
                or (check_size and self._stream.tell() >= self._cfg.rotate_bytes)):
            self._finish_segment()
            self._open_segment()
            self._seg_t0 = t_ns

    def _write(self, item: tuple[Any, ...]) -> None:
        w = self._writer
        assert w is not None
        seq = self._seq & 0xFFFFFFFF
        kind = item[0]
        t_ns = int(item[1])
        log_time = max(t_ns + self._offset, 0)
        if kind == _FRAME:
            _, _, tick, arb, data, is_rx = item
            payload = b'{"tick":%d,"t_ns":%d,"id":%d,"data":"%s","dlc":%d}' % (
                tick, t_ns, arb, data.hex().encode(), len(data))
            ch = self._channels[TOPIC_CAN_RX if is_rx else TOPIC_CAN_TX]
            w.add_message(ch, log_time, payload, log_time, seq)
        elif kind == _TICK:
            record: Mapping[str, Any] = item[2]
            tick = int(record["tick"])
            sig: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
            tim: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
            intl: dict[str, Any] = {"tick": tick, "t_ns": t_ns}
            for k, v in record.items():
                if k in SIGNAL_KEYS:
                    sig[k] = v
                elif k in TIMING_KEYS:
                    tim[k] = v
                elif k not in _RESERVED:
                    intl[k] = v
            parts = [(TOPIC_SIGNALS, sig)]
            parts += [(t, m) for t, m in ((TOPIC_INTERNALS, intl), (TOPIC_TIMING, tim))
                      if len(m) > 2]
            sig[PARTS_KEY] = len(parts)   # lets a reader spot a record torn by a crash
            for topic, msg in parts:
                w.add_message(self._channels[topic], log_time, encode_json(msg),
                              log_time, seq)
        else:
            _, _, tick, kind_s, detail = item
            if kind_s not in EVENT_KINDS:
                detail = {"kind": str(kind_s), "detail": detail}
                kind_s = "note"
            if not (detail is None or isinstance(detail, str | Mapping)):
                detail = str(detail)
            msg = {"tick": int(tick), "t_ns": t_ns, "kind": kind_s,
                   "detail": dict(detail) if isinstance(detail, Mapping) else detail}
            w.add_message(self._channels[TOPIC_EVENTS], log_time, encode_json(msg), log_time, seq)
        self._seq += 1
        self.written += 1

    def _flush(self) -> None:
        """Push finished chunks to the OS; close a chunk older than max_chunk_age_s."""
        assert self._stream is not None
        now = time.monotonic()
        size = self._stream.tell()
        if size != self._last_size:
            self._last_size = size
            self._last_chunk_mono = now
        elif now - self._last_chunk_mono > self._max_chunk_age_s:
            # mcap.Writer has no public "close the open chunk"; 1.x names it like this.
            finalize = getattr(self._writer, "_Writer__finalize_chunk", None)
            if finalize is not None:
                finalize()
            self._last_chunk_mono = now
            self._last_size = self._stream.tell()
        self._stream.flush()

    def _run(self) -> None:
        q = self._q
        try:
            while True:
                closing = self._closing
                n = 0
                while q:
                    item = q.popleft()
                    try:
                        self._maybe_rotate(int(item[1]), n % 64 == 0)
                        self._write(item)
                    except (KeyError, TypeError, ValueError, OverflowError) as exc:
                        self.malformed += 1
                        self.last_malformed = f"{type(exc).__name__}: {exc} in {item[:3]!r}"
                    n += 1
                    if n % 256 == 0:
                        time.sleep(0)  # let the loop thread have the GIL
                if self._failed:
                    return
                self._flush()
                if closing and not q:
                    return
                time.sleep(self._poll_s)
        except OSError as exc:
            self.error = f"recording to {self.paths[-1] if self.paths else '?'} failed: {exc}"
            self._failed = True
            self._dropped += len(q)
            q.clear()


# ---------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class CanFrameRecord:
    index: int            # position in the run (file order across segments)
    t_ns: int
    tick: int
    arbitration_id: int
    data: bytes
    is_rx: bool


@dataclass(frozen=True)
class TickRecord:
    index: int
    t_ns: int
    tick: int
    data: dict[str, Any]  # the record as handed to RunRecorder.tick (JSON round trip)


@dataclass(frozen=True)
class EventRecord:
    index: int
    t_ns: int
    tick: int
    kind: str
    detail: Any


@dataclass
class RunData:
    frames: list[CanFrameRecord] = field(default_factory=list)
    records: list[TickRecord] = field(default_factory=list)
    events: list[EventRecord] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # first segment
    attachments: dict[str, bytes] = field(default_factory=dict)        # first segment
    segments: list[Path] = field(default_factory=list)
    complete: bool = True          # every segment had its footer
    stopped_at: str | None = None  # where and why reading stopped early

    def timeline(self) -> Iterator[CanFrameRecord | TickRecord | EventRecord]:
        """Frames, records and events merged in recording order."""
        items: list[CanFrameRecord | TickRecord | EventRecord] = [
            *self.frames, *self.records, *self.events]
        return iter(sorted(items, key=lambda r: r.index))


def read_run(path: str | Path, *, follow_segments: bool = True) -> RunData:
    """Read a recording (and its rotation successors).  A truncated file (no footer,
    partial chunk) yields everything up to the last complete chunk; ``complete`` is
    False and ``stopped_at`` says where reading stopped.  Reading stops at the first
    incomplete segment (later segments cannot follow a gap)."""
    run = RunData()
    paths = segment_paths(path) if follow_segments else [Path(path)]
    index = 0
    for seg_no, p in enumerate(paths):
        run.segments.append(p)
        index, ok = _read_segment(p, run, index, first=seg_no == 0)
        if not ok:
            break
    return run


def _read_segment(path: Path, run: RunData, index: int, *, first: bool) -> tuple[int, bool]:
    topics: dict[int, str] = {}
    last_rec: tuple[int, dict[str, Any]] | None = None  # (sequence, merged record data)
    parts = [0, 0]  # of the last record: messages expected, messages seen
    n_msgs = 0
    footer = False
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    topic = topics.get(rec.channel_id, "")
                    msg = json.loads(rec.data)
                    n_msgs += 1
                    if topic in _RECORD_TOPICS:
                        if last_rec is not None and last_rec[0] == rec.sequence:
                            bad = last_rec[1].get("nonfinite", []) + msg.get("nonfinite", [])
                            last_rec[1].update(msg)
                            if bad:
                                last_rec[1]["nonfinite"] = bad
                            parts[1] += 1
                            continue
                        last_rec = (rec.sequence, msg)
                        parts[:] = [int(msg.pop(PARTS_KEY, 1)), 1]
                        run.records.append(TickRecord(index, msg["t_ns"], msg["tick"], msg))
                    elif topic in (TOPIC_CAN_RX, TOPIC_CAN_TX):
                        last_rec = None
                        run.frames.append(CanFrameRecord(
                            index, msg["t_ns"], msg["tick"], msg["id"],
                            bytes.fromhex(msg["data"]), topic == TOPIC_CAN_RX))
                    elif topic == TOPIC_EVENTS:
                        last_rec = None
                        run.events.append(EventRecord(index, msg["t_ns"], msg["tick"],
                                                      msg["kind"], msg["detail"]))
                    else:
                        continue
                    index += 1
                elif first and isinstance(rec, Metadata):
                    run.metadata[rec.name] = dict(rec.metadata)
                elif first and isinstance(rec, Attachment):
                    run.attachments[rec.name] = bytes(rec.data)
                elif isinstance(rec, Footer):
                    footer = True
        except Exception as exc:  # truncated / corrupt tail: keep what was complete
            run.complete = False
            run.stopped_at = (f"{path}: {type(exc).__name__} {exc} after {n_msgs} messages "
                              f"(offset {f.tell()} of {path.stat().st_size} bytes)"
                              + _drop_torn_record(run, parts))
            _strip_t_ns(run)
            return index, False
    if not footer:
        run.complete = False
        run.stopped_at = f"{path}: no footer after {n_msgs} messages" + \
            _drop_torn_record(run, parts)
    _strip_t_ns(run)
    return index, footer


def _drop_torn_record(run: RunData, parts: list[int]) -> str:
    """A crash can cut the last tick record between its messages: drop it whole."""
    if run.records and parts[1] < parts[0]:
        torn = run.records.pop()
        return f"; dropped torn record of tick {torn.tick} ({parts[1]}/{parts[0]} parts)"
    return ""


def _strip_t_ns(run: RunData) -> None:
    for r in run.records:
        r.data.pop("t_ns", None)
