"""Replay of recorded runs through the live loop code (``docs/replay.md``).

A replay is one more ``can.BusABC`` behind the project's one bus abstraction:

* :class:`McapReplayBus` hands the loop the received frames of an MCAP recording
  (``rig.recording``), released tick by tick, and keeps what the loop sends;
* :class:`LogReplayBus` does the same for candump ``.log`` / ``.asc`` / ``.blf`` files
  (python-can's ``can.LogReader``), released by timestamp on a virtual tick grid.

:func:`replay_recording` drives an unmodified :class:`rig.loop.ControlLoop` with the
recorded tick times (a virtual clock: no sleeping), the recorded wake-up lateness and
compute time (they feed the overrun check and the heartbeat's p99), re-applies the
recorded operator commands at their ticks and, if the recording ends with a shutdown,
shuts the loop down the same way.  With the recorded design and configuration the
transmitted frames must equal the recorded ones byte for byte; with another design or
configuration the result compares the two controllers on the same sensor data -- open
loop: the recorded plant did not react to the replayed commands.

The MCAP scanner here walks the file itself (``struct`` over the decompressed chunks)
instead of :func:`rig.recording.read_run`, which decodes every message (~25 us/tick):
replay must read a 1 kHz recording 50x faster than real time.  It names what is wrong
with a file (not an MCAP, foreign, wrong version, missing channels, truncated or
corrupt at byte N) and reads a truncated file up to its last complete chunk.
"""

from __future__ import annotations

import binascii
import contextlib
import json
import math
import re
import struct
import tempfile
import time
import tomllib
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import can
import numpy as np
from numpy.typing import NDArray

from controller.artifact import Design, DesignMismatch, load_design
from controller.bank import BankRuntime
from controller.config import RigConfig, config_hash, config_to_toml, parse_config
from controller.force_loop import PIForceLoop
from rig.bus import receive_filters
from rig.loop import ControlLoop
from rig.mcap_schema import (
    MESSAGE_ENCODING,
    RECORDING_FORMAT_VERSION,
    TOPIC_CAN_RX,
    TOPIC_CAN_TX,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_SIGNALS,
    TOPIC_TIMING,
)
from rig.protocol import VALVE_COMMAND, VALVE_COMMAND_ID, LifecycleState, ValveCommand
from rig.recording import (
    CONFIG_ATTACHMENT,
    DESIGN_ATTACHMENT,
    METADATA_NAME,
    RunRecorder,
    segment_paths,
)

__all__ = [
    "LOG_SUFFIXES",
    "LogReplayBus",
    "McapReplayBus",
    "PacedRecorder",
    "RecordedRun",
    "RecordingError",
    "ReplayResult",
    "ScanResult",
    "load_recorded_run",
    "replay_file",
    "replay_log",
    "replay_recording",
    "scan_recording",
    "split_json",
]

#: candump / Vector / python-can log formats read through ``can.LogReader``
LOG_SUFFIXES: Final = (".log", ".asc", ".blf")
OPEN_LOOP_NOTE: Final = ("open loop: the recorded plant did not react to the replayed "
                         "commands (sensor data are the recorded ones)")

MCAP_MAGIC: Final = b"\x89MCAP0\r\n"
#: channels a recording must have to be replayed / reported
REQUIRED_TOPICS: Final = (TOPIC_CAN_RX, TOPIC_CAN_TX, TOPIC_SIGNALS, TOPIC_EVENTS)
RECORDER_LIBRARY_PREFIX: Final = "rig-recorder/"

_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_MESSAGE_INDEX, _OP_ATTACHMENT, _OP_METADATA = 7, 9, 12
_OP_NAMES: Final = {1: "Header", 2: "Footer", 3: "Schema", 4: "Channel", 5: "Message",
                    6: "Chunk", 7: "MessageIndex", 8: "ChunkIndex", 9: "Attachment",
                    10: "AttachmentIndex", 11: "Statistics", 12: "Metadata",
                    13: "MetadataIndex", 14: "SummaryOffset", 15: "DataEnd"}
_REC: Final = struct.Struct("<BQ")        # opcode, record length
_U16: Final = struct.Struct("<H")
_U32: Final = struct.Struct("<I")
_U64: Final = struct.Struct("<Q")
_MSG: Final = struct.Struct("<HIQQ")      # channel id, sequence, log time, publish time
_CHUNK: Final = struct.Struct("<QQQI")    # start, end, uncompressed size, uncompressed crc

#: callback(payloads, sequences): the JSON payloads of one chunk's messages of a wanted
#: topic, concatenated in file order, and their MCAP sequence numbers
Handler = Callable[[bytes, NDArray[np.uint32]], None]
_HEAD_BYTES: Final = np.arange(15)        # opcode, length, channel id, sequence


class RecordingError(ValueError):
    """The file is not a replayable recording; the message names what is wrong."""


@dataclass
class ScanResult:
    segments: list[Path] = field(default_factory=list)
    profile: str = ""
    library: str = ""
    topics: dict[str, str] = field(default_factory=dict)      # topic -> message encoding
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # first segment
    attachments: dict[str, bytes] = field(default_factory=dict)        # first segment
    messages: int = 0
    complete: bool = True
    stopped_at: str | None = None

    @property
    def rig_metadata(self) -> dict[str, str]:
        return self.metadata.get(METADATA_NAME, {})


def _str(buf: bytes | memoryview, off: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, off)
    end = off + 4 + n
    if end > len(buf):
        raise ValueError("string runs past its record")
    return bytes(buf[off + 4:end]).decode("utf-8"), end


def _str_map(buf: bytes | memoryview, off: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    end = off + n
    out: dict[str, str] = {}
    while off < end:
        k, off = _str(buf, off)
        v, off = _str(buf, off)
        out[k] = v
    return out, end


def _decompress(compression: str, data: bytes | memoryview, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return bytes(lz4.frame.decompress(bytes(data)))
    raise ValueError(f"unknown chunk compression {compression!r}")


class _Segment:
    """Walks one file; raises RecordingError for a file that is not a recording.

    A chunk is handed out per wanted channel as one batch.  When the chunk's
    MessageIndex records (written right after it) cover every channel, the payloads are
    gathered with numpy from the indexed offsets; otherwise (first chunk with the
    Channel records, truncated tail, writer without indexes) the chunk's records are
    walked one by one."""

    def __init__(self, path: Path, result: ScanResult, handlers: Mapping[str, Handler],
                 first: bool, after_chunk: Callable[[], None] | None = None) -> None:
        self.after_chunk = after_chunk
        self.path = path
        self.res = result
        self.handlers = handlers
        self.first = first
        self.by_channel: dict[int, Handler | None] = {}
        self.footer = False

    def _channel(self, buf: bytes | memoryview, off: int) -> None:
        (cid,) = _U16.unpack_from(buf, off)
        topic, o = _str(buf, off + 4)
        encoding, _ = _str(buf, o)
        self.res.topics[topic] = encoding
        self.by_channel[cid] = self.handlers.get(topic)

    def _walk(self, buf: bytes) -> int:
        """Walk a chunk's records; returns the number of messages."""
        unpack_rec = _REC.unpack_from
        unpack_msg = _MSG.unpack_from
        parts: dict[int, tuple[list[bytes], list[int]]] = {}
        off, end, n = 0, len(buf), 0
        while off < end:
            op, ln = unpack_rec(buf, off)
            start = off + 9
            off = start + ln
            if op == _OP_MESSAGE:
                cid, seq, _, _ = unpack_msg(buf, start)
                n += 1
                p = parts.get(cid)
                if p is None:
                    p = parts[cid] = ([], [])
                p[0].append(buf[start + 22:off])
                p[1].append(seq)
            elif op == _OP_CHANNEL:
                self._channel(buf, start)
        if off != end:
            raise ValueError("records overrun the chunk")
        for cid, (payloads, seqs) in parts.items():
            h = self.by_channel.get(cid)
            if h is not None:
                h(b"".join(payloads), np.asarray(seqs, dtype=np.uint32))
        return n

    def _gather(self, buf: bytes, index: dict[int, NDArray[np.uint64]]) -> int | None:
        """Hand out the chunk's messages using its MessageIndex offsets; None = walk.

        The indexes carry no CRC, so every offset is checked against the (CRC-checked)
        chunk first -- a Message record of that channel, inside the chunk, records not
        overlapping -- and nothing is handed out unless all channels pass."""
        if not index or any(cid not in self.by_channel for cid in index):
            return None
        n = sum(int(o.size) for o in index.values())
        wanted = [(cid, o) for cid, o in index.items()
                  if self.by_channel[cid] is not None and o.size]
        if not wanted:
            return n
        raw = np.frombuffer(buf, dtype=np.uint8)
        counts = [int(o.size) for _, o in wanted]
        label = np.repeat(np.arange(len(wanted)), counts)
        offs = np.concatenate([o for _, o in wanted]).astype(np.int64)
        order = np.lexsort((offs, label))          # by channel, then file order
        offs = offs[order]
        if offs.min() < 0 or offs.max() + 31 > raw.size:
            return None
        head = raw[offs[:, None] + _HEAD_BYTES]    # opcode, length, channel id, sequence
        if np.any(head[:, 0] != _OP_MESSAGE) or np.any(np.diff(np.sort(offs)) < 31):
            return None
        chan = np.ascontiguousarray(head[:, 9:11]).view("<u2").ravel()
        if np.any(chan != np.array([c for c, _ in wanted])[label]):
            return None
        plen = np.ascontiguousarray(head[:, 1:9]).view("<u8").ravel().astype(np.int64) - 22
        if np.any(plen < 0) or np.any(offs + 31 + plen > raw.size):
            return None
        seqs = np.ascontiguousarray(head[:, 11:15]).view("<u4").ravel()
        starts = (offs + 31).tolist()
        ends = (offs + 31 + plen).tolist()
        i = 0
        for (cid, _), c in zip(wanted, counts, strict=True):
            h = self.by_channel[cid]
            assert h is not None
            h(b"".join([buf[a:b] for a, b in zip(starts[i:i + c], ends[i:i + c],
                                                  strict=True)]), seqs[i:i + c])
            i += c
        return n

    def _chunk(self, buf: bytes, index: dict[int, NDArray[np.uint64]] | None) -> None:
        n = self._gather(buf, index) if index is not None else None
        self.res.messages += self._walk(buf) if n is None else n
        if self.after_chunk is not None:
            try:
                self.after_chunk()
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                if isinstance(exc, RecordingError):
                    raise
                raise RecordingError(f"{self.path}: malformed message payload "
                                     f"({type(exc).__name__}: {exc})") from exc

    def scan(self) -> None:
        path = self.path
        buf = path.read_bytes()
        size = len(buf)
        if buf[:8] != MCAP_MAGIC:
            raise RecordingError(f"{path}: not an MCAP file (first bytes {buf[:8]!r}, "
                                 f"expected {MCAP_MAGIC!r})")
        res = self.res
        view = memoryview(buf)
        pending: bytes | None = None          # a decompressed chunk awaiting its indexes
        index: dict[int, NDArray[np.uint64]] = {}
        off = 8
        while off < size:
            if off + 9 > size:
                self._stop(f"truncated at byte {off} of {size}: incomplete record header")
                break
            op, ln = _REC.unpack_from(buf, off)
            start = off + 9
            end = start + ln
            name = _OP_NAMES.get(op, f"opcode 0x{op:02x}")
            if end > size:
                self._stop(f"truncated at byte {off} of {size}: {name} record of {ln} bytes "
                           "runs past the end of the file")
                break
            try:
                if op == _OP_MESSAGE_INDEX:
                    if pending is not None:
                        (cid,) = _U16.unpack_from(buf, start)
                        (nbytes,) = _U32.unpack_from(buf, start + 2)
                        pairs = np.frombuffer(buf, dtype="<u8", count=nbytes // 8,
                                              offset=start + 6)
                        index[cid] = pairs[1::2]
                    off = end
                    continue
                if pending is not None:       # the chunk's indexes are complete
                    self._chunk(pending, index)
                    pending = None
                if op == _OP_CHUNK:
                    _, _, usize, crc = _CHUNK.unpack_from(buf, start)
                    compression, o = _str(view, start + 28)
                    (rlen,) = _U64.unpack_from(buf, o)
                    raw = _decompress(compression, view[o + 8:o + 8 + rlen], usize)
                    if len(raw) != usize:
                        raise ValueError(f"decompressed {len(raw)} bytes, header says {usize}")
                    if crc and zlib.crc32(raw) != crc:
                        raise ValueError("CRC mismatch")
                    pending, index = raw, {}
                elif op == _OP_MESSAGE:
                    res.messages += self._walk(bytes(buf[off:end]))
                elif op == _OP_CHANNEL:
                    self._channel(view, start)
                elif op == _OP_HEADER:
                    res.profile, o = _str(view, start)
                    res.library, _ = _str(view, o)
                elif op == _OP_METADATA and self.first:
                    mname, o = _str(view, start)
                    res.metadata[mname], _ = _str_map(view, o)
                elif op == _OP_ATTACHMENT and self.first:
                    aname, o = _str(view, start + 16)
                    _, o = _str(view, o)
                    (dlen,) = _U64.unpack_from(buf, o)
                    res.attachments[aname] = bytes(buf[o + 8:o + 8 + dlen])
                elif op == _OP_FOOTER:
                    self.footer = True
                    return
            except RecordingError:
                raise
            except Exception as exc:  # struct.error, ValueError, zstd / lz4 errors ...
                pending = None
                self._stop(f"corrupt {name} record at byte {off} of {size} "
                           f"({type(exc).__name__}: {exc})")
                return
            off = end
        else:
            self._stop(f"no footer (file ends at byte {size})")
        if pending is not None:   # complete chunk, its indexes possibly cut: walk it
            try:
                self._chunk(pending, None)
            except Exception as exc:
                self._stop(f"corrupt chunk before byte {off} ({type(exc).__name__}: {exc})")

    def _stop(self, why: str) -> None:
        self.res.complete = False
        self.res.stopped_at = f"{self.path}: {why}"


def _check_is_recording(res: ScanResult, path: Path) -> None:
    meta = res.rig_metadata
    if not res.complete and not res.topics and not res.library and not meta:
        raise RecordingError(f"{path}: nothing to replay: {res.stopped_at} "
                             "(cut inside the header)")
    if not res.library.startswith(RECORDER_LIBRARY_PREFIX) and not meta:
        raise RecordingError(
            f"{path}: foreign MCAP (profile {res.profile!r}, library {res.library!r}, "
            f"no '{METADATA_NAME}' metadata record; channels {sorted(res.topics) or 'none'})")
    version = meta.get("format_version")
    if version is not None and version != str(RECORDING_FORMAT_VERSION):
        raise RecordingError(f"{path}: recording format version {version}, this software "
                             f"reads version {RECORDING_FORMAT_VERSION}")
    if not res.topics and not res.complete:
        raise RecordingError(f"{path}: nothing to replay: {res.stopped_at} "
                             "(before the first complete chunk)")
    missing = [t for t in REQUIRED_TOPICS if t not in res.topics]
    if missing:
        raise RecordingError(f"{path}: missing channels {missing} (has "
                             f"{sorted(res.topics) or 'none'}; profile {res.profile!r}, "
                             f"library {res.library!r})")
    wrong = [t for t in REQUIRED_TOPICS if res.topics[t] != MESSAGE_ENCODING]
    if wrong:
        raise RecordingError(f"{path}: channels {wrong} are not '{MESSAGE_ENCODING}' encoded")


def scan_recording(path: str | Path, handlers: Mapping[str, Handler], *,
                   follow_segments: bool = True,
                   after_chunk: Callable[[], None] | None = None,
                   result: ScanResult | None = None) -> ScanResult:
    """Scan a recording (and its rotation successors), calling ``handlers[topic]`` with
    each chunk's batch of that topic (see :data:`Handler`), in file order, and
    ``after_chunk()`` after each chunk.

    Raises :class:`RecordingError` (not an MCAP / foreign / wrong version / missing
    channels / nothing readable) and ``FileNotFoundError``.  A truncated or corrupt tail
    ends the scan at the last complete chunk (``complete`` False, ``stopped_at`` says
    where); later segments are then not read."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, expected a .mcap recording")
    res = result if result is not None else ScanResult()
    paths = segment_paths(path) if follow_segments else [path]
    for i, p in enumerate(paths):
        seg = _Segment(p, res, handlers, first=i == 0, after_chunk=after_chunk)
        res.segments.append(p)
        seg.scan()
        if i == 0:
            _check_is_recording(res, p)
        if not seg.footer:
            break
    return res


# ============================================================================ recorded run

_FRAME_RE: Final = re.compile(
    rb'\{"tick":(\d+),"t_ns":(-?\d+),"id":(\d+),"data":"([0-9a-f]*)","dlc":(\d+)\}')


@dataclass
class RecordedRun:
    """What replay needs of a recording: per-tick times and outputs, frames, events."""

    path: Path
    scan: ScanResult
    tick: NDArray[np.int64]            # tick number of each tick record
    t_ns: NDArray[np.int64]            # loop clock of each tick
    lateness_ns: NDArray[np.int64]     # recorded wake-up lateness (0 where not recorded)
    compute_ns: NDArray[np.int64]      # recorded compute time (0 where not recorded)
    spool_cmd: NDArray[np.float64]     # recorded spool command (NaN where null)
    force_ref_n: NDArray[np.float64]   # recorded bank force reference
    valve_enable: NDArray[np.int8]
    rx: list[tuple[int, int, int, bytes]]   # (tick, t_ns, id, data) in read order
    tx: list[tuple[int, int, bytes]]        # (tick, id, data) in send order
    events: list[dict[str, Any]]            # {"tick", "t_ns", "kind", "detail"}
    first_internals: dict[str, Any] | None

    @property
    def complete(self) -> bool:
        return self.scan.complete

    @property
    def stopped_at(self) -> str | None:
        return self.scan.stopped_at

    @property
    def metadata(self) -> dict[str, str]:
        return self.scan.rig_metadata


def _raw_columns(joined: bytes, n: int, keys: Sequence[str]) -> dict[str, NDArray[Any]]:
    """The raw JSON values (bytes array per key) of top-level scalar ``keys`` in ``n``
    concatenated messages.

    Fast path: one regex pass with the keys in the order of the first message (the
    recorder writes compact JSON from the loop's record, same key order every tick; a
    message is one ``{...}`` without nested objects).  Anything else -- a message
    without one of the keys, another order -- fails the count check and every message
    is decoded instead."""
    if n == 0:
        return {key: np.zeros(0, dtype="S4") for key in keys}
    end = joined.find(b"}")
    try:
        first = json.loads(joined[: end + 1]) if end > 0 else {}
    except ValueError:
        first = {}
    order = [k for k in first if k in keys]
    if len(order) == len(keys):
        pattern = re.compile(rb"\{[^{]*?" + rb"[^{]*?".join(
            b'"' + re.escape(k.encode()) + rb'":([^,}\]]*)' for k in order))
        found = pattern.findall(joined)
        if len(found) == n:
            table = np.array(found).reshape(n, len(order))
            return {k: table[:, j] for j, k in enumerate(order)}
    decoded = split_json(joined)
    return {key: np.array([json.dumps(d.get(key)).encode() for d in decoded])
            for key in keys}


def split_json(joined: bytes) -> list[dict[str, Any]]:
    """Decode concatenated JSON objects (a batch of :data:`Handler` payloads)."""
    text = joined.decode("utf-8")
    dec = json.JSONDecoder()
    out: list[dict[str, Any]] = []
    i, n = 0, len(text)
    while i < n:
        obj, i = dec.raw_decode(text, i)
        out.append(obj)
    return out


def _as_f64(a: NDArray[Any]) -> NDArray[np.float64]:
    """JSON numbers (null = NaN) -> float64 (numpy parses like float())."""
    return np.where(a == b"null", b"nan", a).astype(np.float64)


def _as_bool(a: NDArray[Any]) -> NDArray[np.int8]:
    return ((a == b"true") | (a == b"1")).astype(np.int8)


def _as_ns(a: NDArray[Any]) -> NDArray[np.int64]:
    """Seconds (as the loop wrote ``ns * 1e-9``) -> integer ns; null -> 0."""
    return np.nan_to_num(np.rint(_as_f64(a) * 1e9)).astype(np.int64)


def _frames(joined: bytes, n: int) -> list[tuple[int, int, int, bytes]]:
    """(tick, t_ns, id, data) of concatenated /can/rx or /can/tx messages."""
    if n == 0:
        return []
    found = _FRAME_RE.findall(joined)
    if len(found) == n:
        cols = np.array(found)
        tick, t_ns, fid = (cols[:, i].astype(np.int64).tolist() for i in range(3))
        data = list(map(binascii.unhexlify, cols[:, 3].tolist()))
    else:
        decoded = split_json(joined)
        tick = [int(d["tick"]) for d in decoded]
        t_ns = [int(d["t_ns"]) for d in decoded]
        fid = [int(d["id"]) for d in decoded]
        data = [bytes.fromhex(d["data"]) for d in decoded]
    return list(zip(tick, t_ns, fid, data, strict=True))


class _Batches:
    """Collects the batches of one topic."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.seqs: list[NDArray[np.uint32]] = []

    def __call__(self, joined: bytes, seqs: NDArray[np.uint32]) -> None:
        self.parts.append(joined)
        self.seqs.append(seqs)

    @property
    def n(self) -> int:
        return sum(int(s.size) for s in self.seqs)

    def joined(self) -> bytes:
        return b"".join(self.parts)

    def sequence(self) -> NDArray[np.uint32]:
        return np.concatenate(self.seqs) if self.seqs else np.zeros(0, np.uint32)

    def clear(self) -> None:
        self.parts.clear()
        self.seqs.clear()


_SIGNAL_COLUMNS: Final = ("tick", "t_ns", "spool_cmd", "force_ref_n", "valve_enable")
_TIMING_COLUMNS: Final = ("wake_late_s", "compute_s")


@dataclass
class _Piece:
    """A decoded stretch of a recording: the tick records whose timing is known, and
    every frame and event read so far (in file order, so the frames and commands of a
    tick never come after its record)."""

    tick: NDArray[np.int64]
    t_ns: NDArray[np.int64]
    lateness_ns: NDArray[np.int64]
    compute_ns: NDArray[np.int64]
    spool_cmd: NDArray[np.float64]
    force_ref_n: NDArray[np.float64]
    valve_enable: NDArray[np.int8]
    rx: list[tuple[int, int, int, bytes]]
    tx: list[tuple[int, int, bytes]]
    events: list[dict[str, Any]]


def _concat(parts: list[NDArray[Any]], dtype: Any) -> NDArray[Any]:
    return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)


class _RunDecoder:
    """Decodes a scan's batches piece by piece (a piece every ``flush_messages`` tick
    records): the working set stays small however long the recording is, and a reader
    process can hand pieces to the replay while it reads on (``emit``).

    A tick record's ``/rig/timing`` message (same MCAP sequence) may fall into the next
    chunk: trailing records whose timing has not been read yet are held back."""

    def __init__(self, flush_messages: int = 16384,
                 emit: Callable[[_Piece], None] | None = None) -> None:
        self.flush_messages = flush_messages
        self.sig, self.tim, self.internals, self.rx, self.tx, self.events = (
            _Batches() for _ in range(6))
        self.pieces: list[_Piece] = []
        self.emit = emit if emit is not None else self.pieces.append
        self.first: dict[str, Any] | None = None
        self._held: dict[str, NDArray[Any]] = {}
        self._held_seq = np.zeros(0, np.uint32)

    def handlers(self) -> dict[str, Handler]:
        return {TOPIC_SIGNALS: self.sig, TOPIC_TIMING: self.tim,
                TOPIC_INTERNALS: self._on_internals, TOPIC_CAN_RX: self.rx,
                TOPIC_CAN_TX: self.tx, TOPIC_EVENTS: self.events}

    def _on_internals(self, joined: bytes, seqs: NDArray[np.uint32]) -> None:
        if self.first is None and joined:
            self.first, _ = json.JSONDecoder().raw_decode(joined.decode())

    def after_chunk(self) -> None:
        if self.sig.n >= self.flush_messages:
            self.flush()

    def flush(self, final: bool = False) -> None:
        sig = _raw_columns(self.sig.joined(), self.sig.n, _SIGNAL_COLUMNS)
        if self._held:
            sig = {k: np.concatenate((self._held[k], sig[k])) for k in _SIGNAL_COLUMNS}
        sig_seq = np.concatenate((self._held_seq, self.sig.sequence()))
        tim = _raw_columns(self.tim.joined(), self.tim.n, _TIMING_COLUMNS)
        tim_seq = self.tim.sequence()
        t_late, t_comp = _as_ns(tim["wake_late_s"]), _as_ns(tim["compute_s"])
        n = sig_seq.size
        late = np.zeros(n, dtype=np.int64)
        comp = np.zeros(n, dtype=np.int64)
        m = tim_seq.size
        if m <= n and np.array_equal(tim_seq, sig_seq[:m]):
            late[:m] = t_late
            comp[:m] = t_comp
        else:  # a message was lost: attach timing by sequence number
            where = {int(q): i for i, q in enumerate(sig_seq.tolist())}
            for j, q in enumerate(tim_seq.tolist()):
                i = where.get(q)
                if i is not None:
                    late[i] = t_late[j]
                    comp[i] = t_comp[j]
        keep = n
        if not final:  # records after the last timing read: their timing comes later
            keep = int(np.searchsorted(sig_seq, tim_seq.max(), side="right")) if m else 0
            keep = min(keep, n) if np.all(np.diff(sig_seq.astype(np.int64)) > 0) else n
        self._held = {k: sig[k][keep:] for k in _SIGNAL_COLUMNS}
        self._held_seq = sig_seq[keep:]
        self.emit(_Piece(
            tick=sig["tick"][:keep].astype(np.int64), t_ns=sig["t_ns"][:keep].astype(np.int64),
            lateness_ns=late[:keep], compute_ns=comp[:keep],
            spool_cmd=_as_f64(sig["spool_cmd"][:keep]),
            force_ref_n=_as_f64(sig["force_ref_n"][:keep]),
            valve_enable=_as_bool(sig["valve_enable"][:keep]),
            rx=_frames(self.rx.joined(), self.rx.n),
            tx=[(a, c, d) for a, _, c, d in _frames(self.tx.joined(), self.tx.n)],
            events=split_json(self.events.joined())))
        for b in (self.sig, self.tim, self.rx, self.tx, self.events):
            b.clear()


def _assemble(path: Path, scan: ScanResult, pieces: Sequence[_Piece],
              first: dict[str, Any] | None) -> RecordedRun:
    """One RecordedRun from its pieces."""
    def cat(name: str, dtype: Any) -> NDArray[Any]:
        return _concat([getattr(p, name) for p in pieces], dtype)

    return RecordedRun(
        path=path, scan=scan, tick=cat("tick", np.int64), t_ns=cat("t_ns", np.int64),
        lateness_ns=cat("lateness_ns", np.int64), compute_ns=cat("compute_ns", np.int64),
        spool_cmd=cat("spool_cmd", float), force_ref_n=cat("force_ref_n", float),
        valve_enable=cat("valve_enable", np.int8),
        rx=[f for p in pieces for f in p.rx], tx=[f for p in pieces for f in p.tx],
        events=[e for p in pieces for e in p.events], first_internals=first)


def _as_piece(run: RecordedRun) -> _Piece:
    return _Piece(run.tick, run.t_ns, run.lateness_ns, run.compute_ns, run.spool_cmd,
                  run.force_ref_n, run.valve_enable, run.rx, run.tx, run.events)


def _malformed(path: str | Path, exc: Exception) -> RecordingError:
    return RecordingError(f"{path}: malformed message payload ({type(exc).__name__}: "
                          f"{exc})")


def load_recorded_run(path: str | Path) -> RecordedRun:
    """Read what replay needs from a recording (see :func:`scan_recording` for errors)."""
    dec = _RunDecoder()
    scan = scan_recording(path, dec.handlers(), after_chunk=dec.after_chunk)
    try:
        dec.flush(final=True)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise _malformed(path, exc) from exc
    return _assemble(Path(path), scan, dec.pieces, dec.first)


# ---------------------------------------------------------------------------- reader process

#: recordings at least this large are read by a reader process while the loop replays
PIPELINE_MIN_BYTES: Final = 8 * 1024 * 1024


def _reader_main(path: str, conn: Any, flush_messages: int) -> None:
    """Reader process: scan + decode, sending ("head", scan, first internals) after the
    first chunk, ("piece", _Piece) per piece, ("end", scan) or ("error", exception)."""
    try:
        res = ScanResult()
        dec = _RunDecoder(flush_messages, emit=lambda piece: conn.send(("piece", piece)))
        head_sent = False

        def after() -> None:
            nonlocal head_sent
            if not head_sent and res.topics:
                _check_is_recording(res, Path(path))
                conn.send(("head", res, dec.first))
                head_sent = True
            dec.after_chunk()

        scan_recording(path, dec.handlers(), after_chunk=after, result=res)
        try:
            dec.flush(final=True)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise _malformed(path, exc) from exc
        if not head_sent:
            conn.send(("head", res, dec.first))
        conn.send(("end", res))
    except BaseException as exc:  # handed to the replaying process
        conn.send(("error", exc))
    finally:
        conn.close()


class _ReaderProcess:
    """Pieces of a recording from a forked reader process (overlaps reading the MCAP
    with replaying it: each takes about half the time on one core)."""

    def __init__(self, path: Path, flush_messages: int = 16384) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        self.path = path
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_reader_main, args=(str(path), child, flush_messages),
                                 name="rig-replay-reader", daemon=True)
        self._proc.start()
        child.close()
        self.scan: ScanResult | None = None
        self.first: dict[str, Any] | None = None
        self.pieces: list[_Piece] = []
        self._early: list[_Piece] = []
        self._done = False

    def _recv(self) -> tuple[Any, ...]:
        try:
            msg: tuple[Any, ...] = self._conn.recv()
        except EOFError:
            self._proc.join(5.0)
            raise RecordingError(f"{self.path}: reader process ended without a result "
                                 f"(exit code {self._proc.exitcode})") from None
        if msg[0] == "error":
            self._done = True
            raise msg[1]
        return msg

    def head(self) -> tuple[ScanResult, dict[str, Any] | None]:
        while True:
            msg = self._recv()
            if msg[0] == "head":
                return msg[1], msg[2]
            if msg[0] == "piece":
                self._early.append(msg[1])

    def __iter__(self) -> Iterator[_Piece]:
        for piece in self._early:
            self.pieces.append(piece)
            yield piece
        self._early = []
        while not self._done:
            msg = self._recv()
            if msg[0] == "piece":
                self.pieces.append(msg[1])
                yield msg[1]
            elif msg[0] == "end":
                self.scan = msg[1]
                self._done = True

    def close(self) -> None:
        self._conn.close()
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.terminate()   # our own child, by its handle
            self._proc.join(2.0)


# ============================================================================ replay buses


class _ReplayBus(can.BusABC):
    """Frames released by a key (tick or time); sent frames are kept in :attr:`sent`."""

    def __init__(self, keys: Sequence[float], channel: str, *,
                 can_filters: Sequence[Mapping[str, Any]] | None = None) -> None:
        super().__init__(channel=channel, can_filters=None)
        self._keys = keys
        self._n = len(keys)
        self._i = 0
        self._release: float = -math.inf
        self._rx_filters = can_filters
        self.channel_info = channel
        #: (release key at the time of sending, arbitration id, data) in send order
        self.sent: list[tuple[int, int, bytes]] = []
        self.fed = 0       # frames handed to the reader
        self.filtered = 0  # frames skipped by the receive filters

    @property
    def remaining(self) -> int:
        """Frames not yet read."""
        return self._n - self._i

    def release_all(self) -> None:
        """Free-running: every remaining frame is readable now (a plain log player)."""
        self._release = math.inf

    def _message(self, i: int) -> can.Message:
        raise NotImplementedError

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        keys = self._keys
        while self._i < self._n and keys[self._i] <= self._release:
            msg = self._message(self._i)
            self._i += 1
            if self._rx_filters is not None and not self._rx_match(msg):
                self.filtered += 1
                continue
            self.fed += 1
            return msg, True
        return None, True

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next released frame or None -- never waits: in a replay nothing arrives
        while the reader waits (BusABC.recv's timeout bookkeeping is skipped)."""
        return self._recv_internal(timeout)[0]

    def _rx_match(self, msg: can.Message) -> bool:
        filters = self._rx_filters
        if not filters:
            return True
        for f in filters:
            ext = f.get("extended")
            if ext is not None and bool(ext) != msg.is_extended_id:
                continue
            if (msg.arbitration_id ^ f["can_id"]) & f["can_mask"] == 0:
                return True
        return False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        key = self._release
        self.sent.append((int(key) if math.isfinite(key) else -1, msg.arbitration_id,
                          bytes(msg.data)))


class McapReplayBus(_ReplayBus):
    """The received frames of a recording; :meth:`advance` releases those the loop read
    in ticks up to and including ``tick`` (the frames carry their recorded time)."""

    def __init__(self, frames: Sequence[tuple[int, int, int, bytes]],
                 channel: str = "mcap-replay") -> None:
        self._frames: Sequence[tuple[int, int, int, bytes]] = frames
        super().__init__([f[0] for f in frames], channel)

    @classmethod
    def from_file(cls, path: str | Path) -> McapReplayBus:
        run = load_recorded_run(path)
        return cls(run.rx, channel=f"mcap-replay:{Path(path).name}")

    def advance(self, tick: int) -> None:
        self._release = tick

    def extend(self, frames: Sequence[tuple[int, int, int, bytes]]) -> None:
        """More frames (a reader delivers a recording piece by piece)."""
        if not isinstance(self._frames, list):
            self._frames = list(self._frames)
        self._frames.extend(frames)
        assert isinstance(self._keys, list)
        self._keys.extend(f[0] for f in frames)
        self._n = len(self._keys)

    def _message(self, i: int) -> can.Message:
        _, t_ns, fid, data = self._frames[i]
        return can.Message(timestamp=t_ns * 1e-9, arbitration_id=fid, data=data,
                           is_extended_id=fid > 0x7FF, dlc=len(data), is_rx=True,
                           channel=self.channel_info)


class LogReplayBus(_ReplayBus):
    """Frames of a candump ``.log`` / ``.asc`` / ``.blf`` file (``can.LogReader``);
    :meth:`advance_time` releases those stamped at or before ``t_s``.  By default only
    the frames the controller subscribes to pass (``rig.bus.receive_filters``)."""

    def __init__(self, path: str | Path, *, role: str | None = "controller") -> None:
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"{p}: no such log file")
        if p.suffix.lower() not in LOG_SUFFIXES:
            raise RecordingError(f"{p}: unknown log format {p.suffix!r}; replay reads "
                                 f"{', '.join(LOG_SUFFIXES)} and .mcap")
        try:
            with can.LogReader(str(p)) as reader:
                msgs = list(reader)
        except Exception as exc:  # each python-can reader fails its own way
            raise RecordingError(f"{p}: not a readable {p.suffix} log "
                                 f"({type(exc).__name__}: {exc})") from exc
        if not msgs:
            raise RecordingError(f"{p}: no CAN frames in the log")
        msgs.sort(key=lambda m: m.timestamp)   # stable: file order within a timestamp
        self.messages = msgs
        self.start_s = msgs[0].timestamp
        self.end_s = msgs[-1].timestamp
        super().__init__([m.timestamp for m in msgs], f"log-replay:{p.name}",
                         can_filters=receive_filters(role))

    def advance_time(self, t_s: float) -> None:
        self._release = t_s

    def _message(self, i: int) -> can.Message:
        return self.messages[i]

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((-1, msg.arbitration_id, bytes(msg.data)))


# ============================================================================ the driver


class _VirtualClock:
    """The loop's ``clock_ns``: the loop reads it once at the end of a tick (compute
    time = clock - tick time), so it is set to tick time + recorded compute time."""

    __slots__ = ("now_ns",)

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        return self.now_ns


class PacedRecorder:
    """A RunRecorder for a replay that runs faster than real time: waits for the writer
    instead of dropping when too many items are queued (public counters only)."""

    def __init__(self, rec: RunRecorder, limit: int) -> None:
        self.rec = rec
        self.limit = max(16, limit)
        self.submitted = 0

    @property
    def dropped(self) -> int:
        return self.rec.dropped

    def _wait(self) -> None:
        rec = self.rec
        while self.submitted - rec.written - rec.malformed > self.limit and rec.error is None:
            time.sleep(0.0005)

    def can_frame(self, t_ns: int, tick: int, arbitration_id: int, data: bytes | bytearray,
                  is_rx: bool) -> bool:
        self._wait()
        self.submitted += 1
        return self.rec.can_frame(t_ns, tick, arbitration_id, data, is_rx)

    def tick(self, t_ns: int, record: Any) -> bool:
        self._wait()
        self.submitted += 1
        return self.rec.tick(t_ns, record)

    def event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool:
        self._wait()
        self.submitted += 1
        return self.rec.event(t_ns, tick, kind, detail)


@dataclass
class ReplayResult:
    """Outcome of a replay; :meth:`summary` is what ``rig replay --json`` prints."""

    source: str
    kind: str                              # "mcap" or "log"
    same_controller: bool                  # recorded design and config
    ticks: int
    rx_frames_fed: int
    elapsed_s: float
    recorded_s: float
    complete: bool = True
    stopped_at: str | None = None
    tx_frames_recorded: int = 0
    tx_frames_replayed: int = 0
    tx_frames_compared: int = 0
    tx_frames_mismatched: int = 0
    first_mismatch: dict[str, Any] | None = None
    valve_frames_compared: int = 0
    max_abs_command_diff: float = math.nan        # spool command (normalised), per tick
    max_abs_valve_frame_spool_diff: float = math.nan
    max_abs_force_ref_diff_n: float = math.nan
    commands_reapplied: int = 0
    commands_outcome_differs: int = 0
    ticks_missing_in_recording: int = 0
    final_state: str = ""
    faults: list[str] = field(default_factory=list)
    comparison: dict[str, Any] | None = None
    out: str | None = None
    notes: list[str] = field(default_factory=list)
    # per-tick series of the replay (not in the summary)
    tick: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    spool_cmd: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    force_ref_n: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    valve_enable: NDArray[np.int8] = field(default_factory=lambda: np.zeros(0, np.int8))

    @property
    def bit_exact(self) -> bool:
        return (self.same_controller and self.tx_frames_mismatched == 0
                and self.tx_frames_compared == self.tx_frames_recorded
                and self.tx_frames_replayed == self.tx_frames_recorded
                and self.max_abs_command_diff == 0.0
                and self.max_abs_force_ref_diff_n == 0.0)

    @property
    def realtime_factor(self) -> float:
        return self.recorded_s / self.elapsed_s if self.elapsed_s > 0 else math.inf

    def summary(self) -> dict[str, Any]:
        keys = ("source", "kind", "same_controller", "ticks", "rx_frames_fed", "elapsed_s",
                "recorded_s", "complete", "stopped_at", "tx_frames_recorded",
                "tx_frames_replayed", "tx_frames_compared", "tx_frames_mismatched",
                "first_mismatch", "valve_frames_compared", "max_abs_command_diff",
                "max_abs_valve_frame_spool_diff", "max_abs_force_ref_diff_n",
                "commands_reapplied", "commands_outcome_differs",
                "ticks_missing_in_recording", "final_state", "faults", "comparison",
                "out", "notes")
        out = {k: getattr(self, k) for k in keys}
        out["bit_exact"] = self.bit_exact
        out["realtime_factor"] = self.realtime_factor
        return out


def _max_abs_diff(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """max |a - b| with NaN == NaN (both non-finite in the same place counts as equal)."""
    if a.shape != b.shape:
        return math.inf
    if a.size == 0:
        return 0.0
    both_nan = np.isnan(a) & np.isnan(b)
    d = np.abs(np.where(both_nan, 0.0, a - b))
    return float(np.max(np.where(np.isnan(d), np.inf, d)))


def _design_from_bytes(data: bytes) -> Design:
    with tempfile.NamedTemporaryFile(suffix=".npz") as fh:
        fh.write(data)
        fh.flush()
        return load_design(fh.name)


def recorded_config(run: RecordedRun) -> RigConfig:
    raw = run.scan.attachments.get(CONFIG_ATTACHMENT)
    if raw is None:
        raise RecordingError(f"{run.path}: no '{CONFIG_ATTACHMENT}' attachment; "
                             "pass --config")
    try:
        return parse_config(tomllib.loads(raw.decode()))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{run.path}: attachment '{CONFIG_ATTACHMENT}' is not TOML "
                             f"({exc})") from exc


def recorded_design(run: RecordedRun) -> Design:
    raw = run.scan.attachments.get(DESIGN_ATTACHMENT)
    if raw is None:
        raise RecordingError(f"{run.path}: no '{DESIGN_ATTACHMENT}' attachment; "
                             "pass --design")
    try:
        return _design_from_bytes(raw)
    except DesignMismatch as exc:   # e.g. recorded with an older artifact version
        why = str(exc).split(": ", 1)[-1]
        raise RecordingError(f"{run.path}: the recorded design cannot be used ({why}); "
                             "pass --design") from exc


def _runtime_settings(run: RecordedRun, cfg: RigConfig) -> dict[str, Any]:
    """Loop/runtime construction arguments of the recorded run: metadata key ``runtime``
    (a JSON object, see docs/replay.md), else the service's top-level metadata keys
    ``blending`` / ``weight_set`` / ``warmup_ticks``, else the first tick record, else
    the defaults."""
    meta: dict[str, Any] = {}
    for key in ("blending", "weight_set", "warmup_ticks", "single_model"):
        if key in run.metadata:
            with contextlib.suppress(json.JSONDecodeError, TypeError):
                meta[key] = json.loads(run.metadata[key])
    raw = run.metadata.get("runtime")
    if raw:
        with contextlib.suppress(json.JSONDecodeError, TypeError, ValueError):
            meta.update(dict(json.loads(raw)))
    first = run.first_internals or {}
    blending = meta.get("blending", first.get("blending", 0))
    weight_set = meta.get("weight_set", first.get("weight_set", cfg.design.weight_set))
    return {"blending": int(blending), "weight_set": int(weight_set),
            "warmup_ticks": meta.get("warmup_ticks"), "single_model": meta.get("single_model")}


def _build_loop(cfg: RigConfig, design: Design, bus: can.BusABC, settings: Mapping[str, Any],
                clock: Callable[[], int], recorder: Any = None) -> ControlLoop:
    rt = BankRuntime(design, blending=settings["blending"], weight_set=settings["weight_set"],
                     single_model=settings.get("single_model"), cfg=cfg)
    pi = PIForceLoop(cfg.force_loop, cfg.sample_time_s)
    wt = settings.get("warmup_ticks")
    return ControlLoop(cfg, bus, rt, pi, recorder=recorder, blending=settings["blending"],
                       weight_set=settings["weight_set"], clock_ns=clock,
                       warmup_ticks=None if wt is None else int(wt))


def _open_out(out: str | Path, cfg: RigConfig, design_bytes: bytes | None,
              metadata: Mapping[str, Any], clock_offset_ns: int) -> RunRecorder:
    return RunRecorder(out, cfg.recording, config_toml=config_to_toml(cfg),
                       design_bytes=design_bytes, metadata=metadata, clock="replay",
                       clock_offset_ns=clock_offset_ns)


def _apply_commands(loop: ControlLoop, cmds: Sequence[dict[str, Any]]) -> tuple[int, int]:
    """Re-apply recorded commands; (applied, outcome differs from the recording)."""
    differs = 0
    for ev in cmds:
        d = ev["detail"]
        res = loop.request(str(d.get("command")), d.get("argument"), timeout_s=None)
        if "accepted" in d and bool(d["accepted"]) != res.accepted:
            differs += 1
    return len(cmds), differs


def _compare_tx(rec: Sequence[tuple[int, int, bytes]], rep: Sequence[tuple[int, int, bytes]]
                ) -> tuple[int, int, dict[str, Any] | None, int, float]:
    """(compared, mismatched, first mismatch, ValveCommands compared, max spool diff)."""
    n = min(len(rec), len(rep))
    mismatched = 0
    first: dict[str, Any] | None = None
    valves = 0
    max_spool = 0.0
    a, b = ValveCommand(), ValveCommand()
    for i in range(n):
        r, p = rec[i], rep[i]
        if r != p:
            mismatched += 1
            if first is None:
                first = {"index": i, "recorded": {"tick": r[0], "id": r[1], "data": r[2].hex()},
                         "replayed": {"tick": p[0], "id": p[1], "data": p[2].hex()}}
        if r[1] == VALVE_COMMAND_ID and p[1] == VALVE_COMMAND_ID:
            valves += 1
            if r[2] != p[2]:
                VALVE_COMMAND.decode(bytearray(r[2]), a)
                VALVE_COMMAND.decode(bytearray(p[2]), b)
                max_spool = max(max_spool, abs(a.spool_command - b.spool_command))
    if first is None and len(rec) != len(rep):
        i = n
        first = {"index": i, "recorded": None if i >= len(rec) else {"tick": rec[i][0]},
                 "replayed": None if i >= len(rep) else {"tick": rep[i][0]}}
    return n, mismatched, first, valves, max_spool


def _series_comparison(rec: RecordedRun, spool: NDArray[np.float64],
                       fref: NDArray[np.float64], enable: NDArray[np.int8],
                       faults: list[str]) -> dict[str, Any]:
    def rms(x: NDArray[np.float64]) -> float:
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x * x))) if x.size else math.nan

    a, b = rec.force_ref_n, fref
    ok = np.isfinite(a) & np.isfinite(b)
    corr = math.nan
    if ok.sum() > 2 and np.std(a[ok]) > 0 and np.std(b[ok]) > 0:
        corr = float(np.corrcoef(a[ok], b[ok])[0, 1])
    rec_faults = [str(e["detail"].get("fault")) for e in rec.events
                  if e["kind"] == "fault" and isinstance(e["detail"], dict)]
    return {
        "note": OPEN_LOOP_NOTE,
        "force_ref_rms_recorded_n": rms(a),
        "force_ref_rms_replayed_n": rms(b),
        "force_ref_rms_difference_n": rms(a - b),
        "force_ref_correlation": corr,
        "spool_rms_recorded": rms(rec.spool_cmd),
        "spool_rms_replayed": rms(spool),
        "active_ticks_recorded": int(rec.valve_enable.sum()),
        "active_ticks_replayed": int(enable.sum()),
        "faults_recorded": rec_faults,
        "faults_replayed": faults,
    }


class _Replayer:
    """Feeds pieces of a recording through the loop, tick by tick (module docstring)."""

    def __init__(self, loop: ControlLoop, bus: McapReplayBus, clock: _VirtualClock) -> None:
        self.loop = loop
        self.bus = bus
        self.clock = clock
        self.period = loop.period_ns
        self.cmds: dict[int, list[dict[str, Any]]] = {}
        self.stop: dict[str, Any] | None = None
        self.first_tick: int | None = None
        self.next_tick = 0
        self.t_prev = 0
        self.missing = 0
        self.applied = 0
        self.differs = 0
        self.spool: list[float] = []
        self.fref: list[float] = []
        self.enable: list[int] = []

    def _commands(self, cmds: Sequence[dict[str, Any]]) -> None:
        a, d = _apply_commands(self.loop, cmds)
        self.applied += a
        self.differs += d

    def feed(self, piece: _Piece) -> None:
        self.bus.extend(piece.rx)
        for ev in piece.events:
            d = ev.get("detail")
            if ev.get("kind") == "command" and isinstance(d, dict):
                self.cmds.setdefault(int(ev["tick"]), []).append(ev)
            elif ev.get("kind") in ("lifecycle", "fault") and isinstance(d, dict) \
                    and d.get("to") == LifecycleState.STOPPING.name:
                self.stop = ev
        loop, clock, advance, cmds = self.loop, self.clock, self.bus.advance, self.cmds
        tick_fn = loop.tick
        put_spool, put_fref, put_enable = self.spool.append, self.fref.append, \
            self.enable.append
        period = self.period
        for k, t, late, comp in zip(piece.tick.tolist(), piece.t_ns.tolist(),
                                    piece.lateness_ns.tolist(), piece.compute_ns.tolist(),
                                    strict=True):
            if self.first_tick is None:
                self.first_tick = self.next_tick = k
                loop.tick_count = k
                self.t_prev = t - period
            elif k < self.next_tick:     # a repeated tick record: nothing to re-run
                continue
            while self.next_tick <= k:
                kk = self.next_tick
                if kk < k:               # record lost (recorder queue full)
                    self.missing += 1
                    t_k, late_k, comp_k = self.t_prev + period, 0, 0
                else:
                    t_k, late_k, comp_k = t, late, comp
                c = cmds.pop(kk, None)
                if c is not None:
                    self._commands(c)
                advance(kk)
                clock.now_ns = t_k + comp_k
                tick_fn(t_k, late_k)
                put_spool(loop.spool_cmd)
                put_fref(loop.force_ref_n)
                put_enable(loop.enable)
                self.t_prev = t_k
                self.next_tick = kk + 1

    def finish(self) -> None:
        """What the loop did after its last recorded tick: commands, shutdown."""
        if self.first_tick is None:
            return
        self.bus.advance(self.next_tick)
        later = sorted(k for k in self.cmds if k >= self.next_tick)
        for k in later:
            self._commands(self.cmds.pop(k))
        if self.stop is not None:
            self.clock.now_ns = int(self.stop["t_ns"])
            self.loop.shutdown(str(self.stop["detail"].get("reason", "shutdown")))


def _idle_cpu() -> bool:
    """A second CPU is free for the reader (1-minute load average below cores - 1);
    on a busy machine the reader would only slow the loop down."""
    import os

    try:
        return os.getloadavg()[0] < (os.cpu_count() or 1) - 1
    except OSError:
        return False


def replay_recording(path: str | Path, *, cfg: RigConfig | None = None,
                     design: Design | None = None, design_bytes: bytes | None = None,
                     out: str | Path | None = None, run: RecordedRun | None = None,
                     reader_process: bool | None = None) -> ReplayResult:
    """Replay an MCAP recording through :class:`rig.loop.ControlLoop` (module docstring).

    ``cfg`` / ``design`` default to the recording's attachments; given another, the
    result's ``comparison`` compares the two controllers (open loop).  ``out`` writes
    the replay as a new recording (metadata ``replay_of``, ``open_loop``).  ``run``: an
    already loaded recording.  ``reader_process`` reads the file in a forked process
    while replaying (default: for files of at least :data:`PIPELINE_MIN_BYTES` when a
    CPU is idle)."""
    path = Path(path)
    reader: _ReaderProcess | None = None
    if reader_process is None:
        reader_process = (path.is_file() and path.stat().st_size >= PIPELINE_MIN_BYTES
                          and _idle_cpu())
    if run is None and reader_process:
        reader = _ReaderProcess(path)
    try:
        return _replay(path, cfg, design, design_bytes, out, run, reader)
    finally:
        if reader is not None:
            reader.close()


def _replay(path: Path, cfg: RigConfig | None, design: Design | None,
            design_bytes: bytes | None, out: str | Path | None, run: RecordedRun | None,
            reader: _ReaderProcess | None) -> ReplayResult:
    if reader is not None:
        scan, first = reader.head()
        head = RecordedRun(path, scan, *(np.zeros(0, np.int64),) * 4,
                           np.zeros(0), np.zeros(0), np.zeros(0, np.int8), [], [], [], first)
        pieces: Iterable[_Piece] = reader
    else:
        head = run if run is not None else load_recorded_run(path)
        pieces = [_as_piece(head)]
    rec_cfg_raw = head.scan.attachments.get(CONFIG_ATTACHMENT)
    rec_design_raw = head.scan.attachments.get(DESIGN_ATTACHMENT)
    if cfg is None:
        cfg = recorded_config(head)
    if design is None:
        if design_bytes is not None:
            design = _design_from_bytes(design_bytes)
        else:
            design = recorded_design(head)
            design_bytes = rec_design_raw
    same_cfg = rec_cfg_raw is not None and config_hash(cfg) == config_hash(
        parse_config(tomllib.loads(rec_cfg_raw.decode())))
    same_design = rec_design_raw is not None and design_bytes == rec_design_raw
    same = same_cfg and same_design
    settings = _runtime_settings(head, cfg)
    if not same_cfg:   # another configuration brings its own weight set
        settings["weight_set"] = cfg.design.weight_set
    clock = _VirtualClock()
    bus = McapReplayBus([], channel=f"mcap-replay:{head.path.name}")
    recorder: RunRecorder | None = None
    paced: PacedRecorder | None = None
    if out is not None:
        offset = int(head.metadata.get("clock_offset_ns", "0") or 0)
        recorder = _open_out(out, cfg, design_bytes, {
            "source": "rig replay", "replay_of": str(head.path),
            "replay_of_run_id": head.metadata.get("run_id", ""),
            "open_loop": not same, "same_controller": same,
            "runtime": settings}, offset)
        paced = PacedRecorder(recorder, cfg.recording.queue_size // 2)
    loop = _build_loop(cfg, design, bus, settings, clock, paced)
    faults: list[str] = []   # every FAULT transition (loop.transitions keeps the last 256)
    loop.lifecycle.add_listener(
        lambda tr: faults.append(tr.fault_code.name) if tr.state is LifecycleState.FAULT
        else None)
    rp = _Replayer(loop, bus, clock)
    started = time.perf_counter()
    try:
        for piece in pieces:
            rp.feed(piece)
        rp.finish()
    finally:
        elapsed = time.perf_counter() - started
        bus.shutdown()
        if recorder is not None:
            recorder.close()
    if reader is not None:
        assert reader.scan is not None
        run = _assemble(path, reader.scan, reader.pieces, head.first_internals)
    else:
        run = head
    if run.tick.size == 0 or rp.first_tick is None:
        raise RecordingError(f"{run.path}: no tick records to replay"
                             + (f" ({run.stopped_at})" if run.stopped_at else ""))
    return _result(run, rp, loop, bus, same, faults, elapsed, recorder, out)


def _result(run: RecordedRun, rp: _Replayer, loop: ControlLoop, bus: McapReplayBus,
            same: bool, faults: list[str], elapsed: float, recorder: RunRecorder | None,
            out: str | Path | None) -> ReplayResult:
    """Compare the replay with the recording."""
    notes: list[str] = []
    if not run.complete:
        notes.append(f"recording incomplete, replayed up to its last complete chunk: "
                     f"{run.stopped_at}")
    if rp.missing:
        notes.append(f"{rp.missing} ticks missing from the recording (dropped): replayed "
                     "with interpolated times and zero lateness")
    first_tick = int(rp.first_tick or 0)
    last_tick = rp.next_tick - 1
    spool = np.asarray(rp.spool, dtype=float)
    fref = np.asarray(rp.fref, dtype=float)
    enable = np.asarray(rp.enable, dtype=np.int8)
    rec_tx, rep_tx = run.tx, bus.sent
    if not run.complete:  # the cut may fall inside a tick: its frames are incomplete
        rec_tx = [f for f in run.tx if f[0] <= last_tick]
        rep_tx = [f for f in bus.sent if f[0] <= last_tick]
        if len(rec_tx) < len(run.tx) or len(rep_tx) < len(bus.sent):
            notes.append("frames sent after the last complete tick record were not "
                         f"compared ({len(run.tx) - len(rec_tx)} recorded, "
                         f"{len(bus.sent) - len(rep_tx)} replayed)")
    compared, mism, first, valves, vspool = _compare_tx(rec_tx, rep_tx)
    pos = run.tick - first_tick       # replayed series at the recorded ticks
    period = rp.period
    res = ReplayResult(
        source=str(run.path), kind="mcap", same_controller=same, ticks=spool.size,
        rx_frames_fed=bus.fed, elapsed_s=elapsed,
        recorded_s=(int(run.t_ns[-1]) - int(run.t_ns[0]) + period) * 1e-9,
        complete=run.complete, stopped_at=run.stopped_at,
        tx_frames_recorded=len(rec_tx), tx_frames_replayed=len(rep_tx),
        tx_frames_compared=compared, tx_frames_mismatched=mism, first_mismatch=first,
        valve_frames_compared=valves,
        max_abs_command_diff=_max_abs_diff(run.spool_cmd, spool[pos]),
        max_abs_valve_frame_spool_diff=vspool,
        max_abs_force_ref_diff_n=_max_abs_diff(run.force_ref_n, fref[pos]),
        commands_reapplied=rp.applied, commands_outcome_differs=rp.differs,
        ticks_missing_in_recording=rp.missing, final_state=loop.lifecycle.state.name,
        faults=faults, out=None if recorder is None else str(recorder.base_path),
        notes=notes, tick=np.arange(first_tick, last_tick + 1, dtype=np.int64),
        spool_cmd=spool, force_ref_n=fref, valve_enable=enable)
    if recorder is not None and recorder.error:
        notes.append(f"writing {out}: {recorder.error}")
    if not same:
        res.comparison = _series_comparison(run, spool[pos], fref[pos], enable[pos], faults)
        notes.append(OPEN_LOOP_NOTE)
    return res


def replay_log(path: str | Path, cfg: RigConfig, design: Design, *,
               design_bytes: bytes | None = None, arm_at_s: float | None = None,
               out: str | Path | None = None) -> ReplayResult:
    """Replay a candump ``.log`` / ``.asc`` / ``.blf`` file: ticks on a grid of the
    sample period starting half a period after the first frame (a frame belongs to the
    first tick at or after its timestamp), decoded with the project's DBC codec.  A log
    carries no commands: the controller stays INACTIVE (computing its force reference)
    unless ``arm_at_s`` (seconds after the first frame) arms it."""
    bus = LogReplayBus(path)
    clock = _VirtualClock()
    settings = {"blending": 0, "weight_set": cfg.design.weight_set, "warmup_ticks": None,
                "single_model": None}
    recorder: RunRecorder | None = None
    paced: PacedRecorder | None = None
    if out is not None:
        recorder = _open_out(out, cfg, design_bytes, {
            "source": "rig replay", "replay_of": str(path), "open_loop": True,
            "runtime": settings}, 0)
        paced = PacedRecorder(recorder, cfg.recording.queue_size // 2)
    loop = _build_loop(cfg, design, bus, settings, clock, paced)
    faults: list[str] = []   # every FAULT transition (loop.transitions keeps the last 256)
    loop.lifecycle.add_listener(
        lambda tr: faults.append(tr.fault_code.name) if tr.state is LifecycleState.FAULT
        else None)
    period = loop.period_ns
    t0_ns = round(bus.start_s * 1e9) + period // 2
    span_ns = round((bus.end_s - bus.start_s) * 1e9)
    n = max(0, span_ns - period // 2 + period - 1) // period + 1   # last frame's tick + 1
    arm_tick = None if arm_at_s is None else round(arm_at_s * 1e9 / period)
    spool, fref = np.empty(n), np.empty(n)
    enable = np.empty(n, dtype=np.int8)
    notes = [OPEN_LOOP_NOTE]
    started = time.perf_counter()
    try:
        for k in range(n):
            if k == arm_tick:
                res = loop.request("arm", timeout_s=None)
                if not res.accepted:
                    notes.append(f"arm at tick {k} refused: {res.message}")
            t = t0_ns + k * period
            bus.advance_time(t * 1e-9)
            clock.now_ns = t
            loop.tick(t, 0)
            spool[k] = loop.spool_cmd
            fref[k] = loop.force_ref_n
            enable[k] = loop.enable
    finally:
        elapsed = time.perf_counter() - started
        bus.shutdown()
        if recorder is not None:
            recorder.close()
    if bus.filtered:
        notes.append(f"{bus.filtered} frames not for the controller (receive filters) "
                     "were skipped")
    return ReplayResult(
        source=str(path), kind="log", same_controller=False, ticks=n,
        rx_frames_fed=bus.fed, elapsed_s=elapsed, recorded_s=n * period * 1e-9,
        tx_frames_replayed=len(bus.sent), final_state=loop.lifecycle.state.name,
        faults=faults, out=None if recorder is None else str(recorder.base_path),
        notes=notes, tick=np.arange(n, dtype=np.int64), spool_cmd=spool, force_ref_n=fref,
        valve_enable=enable)


def replay_file(path: str | Path, *, cfg: RigConfig | None = None,
                design: Design | None = None, design_bytes: bytes | None = None,
                out: str | Path | None = None, arm_at_s: float | None = None
                ) -> ReplayResult:
    """Replay an ``.mcap`` recording or a python-can log file (by suffix)."""
    p = Path(path)
    if p.suffix.lower() in LOG_SUFFIXES:
        if cfg is None:
            raise RecordingError(f"{p}: a log file carries no configuration")
        if design is None:
            raise RecordingError(f"{p}: a log file carries no design")
        return replay_log(p, cfg, design, design_bytes=design_bytes, arm_at_s=arm_at_s,
                          out=out)
    return replay_recording(p, cfg=cfg, design=design, design_bytes=design_bytes, out=out)

