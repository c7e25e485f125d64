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

import contextlib
import json
import math
import re
import struct
import tempfile
import time
import tomllib
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import can
import numpy as np
from numpy.typing import NDArray

from controller.artifact import Design, load_design
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
_OP_ATTACHMENT, _OP_METADATA = 9, 12
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

#: callback(payload, sequence) for one message of a wanted topic
Handler = Callable[[bytes, int], None]


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
    """Walks one file; raises RecordingError for a file that is not a recording."""

    def __init__(self, path: Path, result: ScanResult, handlers: Mapping[str, Handler],
                 first: bool) -> None:
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

    def _messages(self, buf: bytes, off: int, end: int) -> int:
        """Walk the records in buf[off:end] (a chunk's content); returns messages seen."""
        unpack_rec = _REC.unpack_from
        unpack_msg = _MSG.unpack_from
        by_channel = self.by_channel
        n = 0
        while off < end:
            op, ln = unpack_rec(buf, off)
            start = off + 9
            off = start + ln
            if op == _OP_MESSAGE:
                cid, seq, _, _ = unpack_msg(buf, start)
                n += 1
                h = by_channel.get(cid)
                if h is not None:
                    h(buf[start + 22:off], seq)
            elif op == _OP_CHANNEL:
                self._channel(buf, start)
        if off != end:
            raise ValueError("records overrun the chunk")
        return n

    def scan(self) -> None:
        path = self.path
        buf = path.read_bytes()
        size = len(buf)
        if buf[:8] != MCAP_MAGIC:
            raise RecordingError(f"{path}: not an MCAP file (first bytes {buf[:8]!r}, "
                                 f"expected {MCAP_MAGIC!r})")
        res = self.res
        view = memoryview(buf)
        off = 8
        while off < size:
            if off + 9 > size:
                self._stop(f"truncated at byte {off} of {size}: incomplete record header")
                return
            op, ln = _REC.unpack_from(buf, off)
            start = off + 9
            end = start + ln
            name = _OP_NAMES.get(op, f"opcode 0x{op:02x}")
            if end > size:
                self._stop(f"truncated at byte {off} of {size}: {name} record of {ln} bytes "
                           "runs past the end of the file")
                return
            try:
                if op == _OP_CHUNK:
                    _, _, usize, crc = _CHUNK.unpack_from(buf, start)
                    compression, o = _str(view, start + 28)
                    (rlen,) = _U64.unpack_from(buf, o)
                    raw = _decompress(compression, view[o + 8:o + 8 + rlen], usize)
                    if len(raw) != usize:
                        raise ValueError(f"decompressed {len(raw)} bytes, header says {usize}")
                    if crc and zlib.crc32(raw) != crc:
                        raise ValueError("CRC mismatch")
                    res.messages += self._messages(raw, 0, len(raw))
                elif op == _OP_MESSAGE:
                    cid, seq, _, _ = _MSG.unpack_from(buf, start)
                    res.messages += 1
                    h = self.by_channel.get(cid)
                    if h is not None:
                        h(buf[start + 22:end], seq)
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
            except (ValueError, struct.error, UnicodeDecodeError) as exc:
                if isinstance(exc, RecordingError):
                    raise
                self._stop(f"corrupt {name} record at byte {off} of {size} ({exc})")
                return
            except Exception as exc:  # zstandard.ZstdError, lz4 RuntimeError ...
                self._stop(f"corrupt {name} record at byte {off} of {size} "
                           f"({type(exc).__name__}: {exc})")
                return
            off = end
        self._stop(f"no footer (file ends at byte {size})")

    def _stop(self, why: str) -> None:
        self.res.complete = False
        self.res.stopped_at = f"{self.path}: {why}"


def _check_is_recording(res: ScanResult, path: Path) -> None:
    meta = res.rig_metadata
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
                   follow_segments: bool = True) -> ScanResult:
    """Scan a recording (and its rotation successors), calling ``handlers[topic]`` with
    each message's raw payload and MCAP sequence, in file order.

    Raises :class:`RecordingError` (not an MCAP / foreign / wrong version / missing
    channels / nothing readable) and ``FileNotFoundError``.  A truncated or corrupt tail
    ends the scan at the last complete chunk (``complete`` False, ``stopped_at`` says
    where); later segments are then not read."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, expected a .mcap recording")
    res = ScanResult()
    paths = segment_paths(path) if follow_segments else [path]
    for i, p in enumerate(paths):
        seg = _Segment(p, res, handlers, first=i == 0)
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


def _parse_frame(payload: bytes) -> tuple[int, int, int, bytes]:
    """(tick, t_ns, arbitration id, data) of a /can/rx or /can/tx message."""
    m = _FRAME_RE.fullmatch(payload)
    if m is not None:
        return int(m[1]), int(m[2]), int(m[3]), bytes.fromhex(m[4].decode())
    d = json.loads(payload)  # another key order / extra fields: the slow, general way
    return int(d["tick"]), int(d["t_ns"]), int(d["id"]), bytes.fromhex(d["data"])


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

    def commands_by_tick(self) -> dict[int, list[dict[str, Any]]]:
        out: dict[int, list[dict[str, Any]]] = {}
        for ev in self.events:
            if ev["kind"] == "command" and isinstance(ev["detail"], dict):
                out.setdefault(int(ev["tick"]), []).append(ev)
        return out

    def stop_event(self) -> dict[str, Any] | None:
        """The lifecycle transition to STOPPING (a recorded shutdown), if any."""
        for ev in self.events:
            d = ev["detail"]
            if ev["kind"] in ("lifecycle", "fault") and isinstance(d, dict) \
                    and d.get("to") == LifecycleState.STOPPING.name:
                return ev
        return None


def _values(joined: bytes, key: str, n: int) -> list[bytes] | None:
    """The raw JSON values of top-level scalar ``key`` in ``n`` joined messages, or None
    when the key is not there exactly once per message (then parse each message)."""
    vals: list[bytes] = re.findall(b'"' + key.encode() + rb'":([^,}\]]*)', joined)
    return vals if len(vals) == n else None


def _columns(payloads: list[bytes], spec: Mapping[str, Callable[[bytes], Any]]
             ) -> dict[str, list[Any]]:
    """Columns ``spec`` (key -> converter of the raw JSON value) of JSON messages.

    Fast path: one regex pass per key over all payloads (the recorder writes compact
    JSON); a key missing from some message falls back to ``json.loads`` per message."""
    n = len(payloads)
    joined = b"\n".join(payloads)
    out: dict[str, list[Any]] = {}
    for key, conv in spec.items():
        vals = _values(joined, key, n)
        if vals is None:
            vals = [json.dumps(json.loads(p).get(key)).encode() for p in payloads]
        out[key] = [conv(v) for v in vals]
    return out


def _f64(v: bytes) -> float:
    return math.nan if v == b"null" else float(v)


def _bool01(v: bytes) -> int:
    return 1 if v == b"true" or v == b"1" else 0


def _ns(v: bytes) -> int:
    return 0 if v == b"null" else round(float(v) * 1e9)


def _frames(payloads: list[bytes]) -> list[tuple[int, int, int, bytes]]:
    joined = b"\n".join(payloads)
    found = _FRAME_RE.findall(joined)
    if len(found) != len(payloads):
        return [_parse_frame(p) for p in payloads]
    fromhex = bytes.fromhex
    return [(int(a), int(b), int(c), fromhex(d.decode())) for a, b, c, d, _ in found]


def load_recorded_run(path: str | Path) -> RecordedRun:
    """Read what replay needs from a recording (see :func:`scan_recording` for errors)."""
    sig: list[bytes] = []
    sig_seq: list[int] = []
    tim: list[bytes] = []
    tim_seq: list[int] = []
    rx: list[bytes] = []
    tx: list[bytes] = []
    events: list[bytes] = []
    first_internals: list[bytes] = []

    def on_internals(payload: bytes, seq: int) -> None:
        if not first_internals:
            first_internals.append(payload)

    def on_signals(payload: bytes, seq: int) -> None:
        sig.append(payload)
        sig_seq.append(seq)

    def on_timing(payload: bytes, seq: int) -> None:
        tim.append(payload)
        tim_seq.append(seq)

    scan = scan_recording(path, {
        TOPIC_SIGNALS: on_signals,
        TOPIC_TIMING: on_timing,
        TOPIC_INTERNALS: on_internals,
        TOPIC_CAN_RX: lambda p, s: rx.append(p),
        TOPIC_CAN_TX: lambda p, s: tx.append(p),
        TOPIC_EVENTS: lambda p, s: events.append(p)})
    try:
        s = _columns(sig, {"tick": int, "t_ns": int, "spool_cmd": _f64, "force_ref_n": _f64,
                           "valve_enable": _bool01})
        t = _columns(tim, {"wake_late_s": _ns, "compute_s": _ns})
        rx_frames = _frames(rx)
        tx_frames = [(a, c, d) for a, _, c, d in _frames(tx)]
        ev = [json.loads(p) for p in events]
        first = json.loads(first_internals[0]) if first_internals else None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise RecordingError(f"{path}: malformed message payload ({type(exc).__name__}: "
                             f"{exc})") from exc
    n = len(sig)
    late = np.zeros(n, dtype=np.int64)
    comp = np.zeros(n, dtype=np.int64)
    if tim:
        if tim_seq == sig_seq:
            late[:] = t["wake_late_s"]
            comp[:] = t["compute_s"]
        else:  # a message was lost: attach timing by sequence number
            where = {q: i for i, q in enumerate(sig_seq)}
            for j, q in enumerate(tim_seq):
                i = where.get(q)
                if i is not None:
                    late[i] = t["wake_late_s"][j]
                    comp[i] = t["compute_s"][j]
    return RecordedRun(
        path=Path(path), scan=scan,
        tick=np.asarray(s["tick"], dtype=np.int64), t_ns=np.asarray(s["t_ns"], dtype=np.int64),
        lateness_ns=late, compute_ns=comp,
        spool_cmd=np.asarray(s["spool_cmd"], dtype=float),
        force_ref_n=np.asarray(s["force_ref_n"], dtype=float),
        valve_enable=np.asarray(s["valve_enable"], dtype=np.int8), rx=rx_frames, tx=tx_frames,
        events=ev, first_internals=first)


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
        self.channel_info = f"{channel} ({self._n} frames)"
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
        self._frames = frames
        super().__init__([f[0] for f in frames], channel)

    @classmethod
    def from_file(cls, path: str | Path) -> McapReplayBus:
        run = load_recorded_run(path)
        return cls(run.rx, channel=f"mcap-replay:{Path(path).name}")

    def advance(self, tick: int) -> None:
        self._release = tick

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
    return _design_from_bytes(raw)


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


def replay_recording(path: str | Path, *, cfg: RigConfig | None = None,
                     design: Design | None = None, design_bytes: bytes | None = None,
                     out: str | Path | None = None,
                     run: RecordedRun | None = None) -> ReplayResult:
    """Replay an MCAP recording through :class:`rig.loop.ControlLoop` (module docstring).

    ``cfg`` / ``design`` default to the recording's attachments; given another, the
    result's ``comparison`` compares the two controllers (open loop).  ``out`` writes
    the replay as a new recording (metadata ``replay_of``, ``open_loop``)."""
    run = run if run is not None else load_recorded_run(path)
    rec_cfg_raw = run.scan.attachments.get(CONFIG_ATTACHMENT)
    rec_design_raw = run.scan.attachments.get(DESIGN_ATTACHMENT)
    if cfg is None:
        cfg = recorded_config(run)
    if design is None:
        if design_bytes is not None:
            design = _design_from_bytes(design_bytes)
        else:
            design = recorded_design(run)
            design_bytes = rec_design_raw
    same_cfg = rec_cfg_raw is not None and config_hash(cfg) == config_hash(
        parse_config(tomllib.loads(rec_cfg_raw.decode())))
    same_design = rec_design_raw is not None and design_bytes == rec_design_raw
    same = same_cfg and same_design
    notes: list[str] = []
    if not run.complete:
        notes.append(f"recording incomplete, replayed up to its last complete chunk: "
                     f"{run.stopped_at}")
    if run.tick.size == 0:
        raise RecordingError(f"{run.path}: no tick records to replay"
                             + (f" ({run.stopped_at})" if run.stopped_at else ""))

    settings = _runtime_settings(run, cfg)
    if not same_cfg:   # another configuration brings its own weight set
        settings["weight_set"] = cfg.design.weight_set
    clock = _VirtualClock()
    bus = McapReplayBus(run.rx, channel=f"mcap-replay:{run.path.name}")
    recorder: RunRecorder | None = None
    paced: PacedRecorder | None = None
    if out is not None:
        offset = int(run.metadata.get("clock_offset_ns", "0") or 0)
        recorder = _open_out(out, cfg, design_bytes, {
            "source": "rig replay", "replay_of": str(run.path),
            "replay_of_run_id": run.metadata.get("run_id", ""),
            "open_loop": not same, "same_controller": same,
            "runtime": settings}, offset)
        paced = PacedRecorder(recorder, cfg.recording.queue_size // 2)
    loop = _build_loop(cfg, design, bus, settings, clock, paced)
    period = loop.period_ns

    first_tick, last_tick = int(run.tick[0]), int(run.tick[-1])
    n = last_tick - first_tick + 1
    index = np.full(n, -1, dtype=np.int64)
    index[run.tick - first_tick] = np.arange(run.tick.size)
    missing = int(np.count_nonzero(index < 0))
    if missing:
        notes.append(f"{missing} ticks missing from the recording (dropped): replayed with "
                     "interpolated times and zero lateness")
    cmds = run.commands_by_tick()
    spool = np.empty(n)
    fref = np.empty(n)
    enable = np.empty(n, dtype=np.int8)
    t_ns_arr, late_arr, comp_arr = run.t_ns.tolist(), run.lateness_ns.tolist(), \
        run.compute_ns.tolist()
    idx = index.tolist()
    applied = differs = 0
    loop.tick_count = first_tick
    tick_fn = loop.tick
    advance = bus.advance
    t_prev = int(run.t_ns[0]) - period
    started = time.perf_counter()
    try:
        for i in range(n):
            k = first_tick + i
            c = cmds.get(k)
            if c is not None:
                a_, d_ = _apply_commands(loop, c)
                applied += a_
                differs += d_
            j = idx[i]
            if j >= 0:
                t, late, comp = t_ns_arr[j], late_arr[j], comp_arr[j]
            else:
                t, late, comp = t_prev + period, 0, 0
            t_prev = t
            advance(k)
            clock.now_ns = t + comp
            tick_fn(t, late)
            spool[i] = loop.spool_cmd
            fref[i] = loop.force_ref_n
            enable[i] = loop.enable
        advance(last_tick + 1)   # what the loop does after its last tick
        end_cmds = [c for k, cs in cmds.items() if k > last_tick for c in cs]
        if end_cmds:
            a_, d_ = _apply_commands(loop, end_cmds)
            applied += a_
            differs += d_
        stop = run.stop_event()
        if stop is not None:
            clock.now_ns = int(stop["t_ns"])
            loop.shutdown(str(stop["detail"].get("reason", "shutdown")))
    finally:
        elapsed = time.perf_counter() - started
        bus.shutdown()
        if recorder is not None:
            recorder.close()
    faults = [tr.fault_code.name for tr in loop.transitions
              if tr.state is LifecycleState.FAULT]
    compared, mism, first, valves, vspool = _compare_tx(run.tx, bus.sent)
    pos = run.tick - first_tick       # replayed series at the recorded ticks
    res = ReplayResult(
        source=str(run.path), kind="mcap", same_controller=same, ticks=n,
        rx_frames_fed=bus.fed, elapsed_s=elapsed,
        recorded_s=(int(run.t_ns[-1]) - int(run.t_ns[0]) + period) * 1e-9,
        complete=run.complete, stopped_at=run.stopped_at,
        tx_frames_recorded=len(run.tx), tx_frames_replayed=len(bus.sent),
        tx_frames_compared=compared, tx_frames_mismatched=mism, first_mismatch=first,
        valve_frames_compared=valves,
        max_abs_command_diff=_max_abs_diff(run.spool_cmd, spool[pos]),
        max_abs_valve_frame_spool_diff=vspool,
        max_abs_force_ref_diff_n=_max_abs_diff(run.force_ref_n, fref[pos]),
        commands_reapplied=applied, commands_outcome_differs=differs,
        ticks_missing_in_recording=missing, final_state=loop.lifecycle.state.name,
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
    faults = [tr.fault_code.name for tr in loop.transitions
              if tr.state is LifecycleState.FAULT]
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

