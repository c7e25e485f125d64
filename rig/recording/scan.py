"""The one MCAP reader of recordings: walks a recording's records itself.

:func:`scan_recording` hands each wanted topic one batch per chunk (the JSON payloads
of the chunk's messages of that topic, concatenated, with their MCAP sequence numbers)
instead of decoding every message into Python objects: replay must read a 1 kHz
recording 50x faster than real time.  Every reader of recordings is built on it:
replay (:mod:`rig.replay.recorded`), the report (:mod:`rig.report.series`) and the
Python API :func:`rig.recording.run_data.read_run` (every frame, record and event as
objects).  It names what is wrong with a file (not an MCAP, foreign, another format
version, missing channels, truncated or corrupt at byte N, damaged summary or closing
magic, a missing or foreign segment of a run) and reads a truncated file up to its last
complete chunk (docs/recording.md, "Reading"; docs/replay.md, "The scanner").  A file
is read record by record: memory holds one chunk, whatever the size of the file.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Final

import numpy as np
from numpy.typing import NDArray

from controller.files import NotRegularFileError, open_regular
from rig.recording.schema import (
    MESSAGE_ENCODING,
    METADATA_NAME,
    RECORDING_FORMAT_VERSION,
    TOPIC_CAN_RX,
    TOPIC_CAN_TX,
    TOPIC_EVENTS,
    TOPIC_SIGNALS,
)
from rig.recording.segments import (
    MCAP_MAGIC,
    SEGMENT_END_NAME,
    SegmentChain,
    SegmentHead,
    next_segment,
    tail_problem,
)

__all__ = [
    "MCAP_MAGIC",
    "RECORDER_LIBRARY_PREFIX",
    "REQUIRED_TOPICS",
    "Handler",
    "RecordingError",
    "ScanResult",
    "check_is_recording",
    "scan_recording",
    "split_json",
]

#: channels a recording must have to be replayed / reported
REQUIRED_TOPICS: Final = (TOPIC_CAN_RX, TOPIC_CAN_TX, TOPIC_SIGNALS, TOPIC_EVENTS)
RECORDER_LIBRARY_PREFIX: Final = "rig-recorder/"

_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_MESSAGE_INDEX, _OP_ATTACHMENT, _OP_METADATA, _OP_DATA_END = 7, 9, 12, 15
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
    """The file is not a readable recording; the message names what is wrong."""


def version_problem(path: Path, version: str) -> str:
    """'' for this software's format version, else the one-line refusal."""
    if version == str(RECORDING_FORMAT_VERSION):
        return ""
    return (f"{path}: recording format version {version}, this software reads version "
            f"{RECORDING_FORMAT_VERSION} only")


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


@dataclass
class ScanResult:
    segments: list[Path] = field(default_factory=list)
    profile: str = ""
    library: str = ""
    topics: dict[str, str] = field(default_factory=dict)      # topic -> message encoding
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # first segment
    attachments: dict[str, bytes] = field(default_factory=dict)        # first segment
    #: attachments of the first segment that failed their CRC (name -> what is wrong);
    #: they are not in ``attachments``
    damaged_attachments: dict[str, str] = field(default_factory=dict)
    messages: int = 0
    complete: bool = True          # every segment present, intact, with its footer
    stopped_at: str | None = None  # where and why reading stopped
    notes: list[str] = field(default_factory=list)  # e.g. a stale file after the run

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
                 first: bool, after_chunk: Callable[[], None] | None = None,
                 chain: SegmentChain | None = None) -> None:
        self.path, self.res, self.handlers, self.chain = path, result, handlers, chain
        self.first, self.after_chunk = first, after_chunk
        self.by_channel: dict[int, Handler | None] = {}
        self.footer = False
        # a later segment of a run: nothing of it is used before its identity is checked
        self.accepted = first or chain is None
        self.refused = False
        self.end: dict[str, str] | None = None   # its rig_segment_end metadata

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

    def _metadata(self, name: str, meta: dict[str, str]) -> bool:
        """A Metadata record; False when the segment is refused (not this run's)."""
        if self.first:
            self.res.metadata[name] = meta
        if name == SEGMENT_END_NAME:
            self.end = meta
        elif name == METADATA_NAME and self.first:
            # another format version is refused before any of its data is handed out
            problem = version_problem(self.path, meta.get("format_version", "(none)"))
            if not problem and self.chain is not None:
                problem = self.chain.check_first(SegmentHead.parse(meta))
            if problem:
                raise RecordingError(problem)
        elif name == METADATA_NAME and self.chain is not None:
            problem = self.chain.check_head(self.path, SegmentHead.parse(meta))
            if problem:
                self._refuse(problem)
                return False
            self.accepted = True
        return True

    def _refuse(self, why: str) -> None:
        self.refused = True
        self.res.complete = False
        self.res.stopped_at = why

    def _open(self) -> tuple[BinaryIO, int]:
        """The file, positioned after its first 8 bytes (found to be the MCAP magic: a
        device or a large file of something else is never read), and its size (the
        bytes read when it is cut inside the magic)."""
        path = self.path
        try:
            f = open_regular(path)
        except NotRegularFileError as exc:
            raise RecordingError(str(exc)) from None
        try:
            magic = f.read(len(MCAP_MAGIC))
            if len(magic) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(magic):
                return f, len(magic)          # cut inside the magic (scan() says so)
            if magic != MCAP_MAGIC:
                raise RecordingError(f"{path}: not an MCAP file (first bytes {magic!r}, "
                                     f"expected {MCAP_MAGIC!r})")
            return f, os.fstat(f.fileno()).st_size
        except BaseException:
            f.close()
            raise

    def scan(self) -> None:
        f, size = self._open()
        with f:
            self._scan(f, size)

    def _scan(self, f: BinaryIO, size: int) -> None:
        """Read the records one at a time (memory: one record, i.e. one chunk, whatever
        the size of the file), the data section's CRC running over them."""
        path = self.path
        res = self.res
        pending: bytes | None = None          # a decompressed chunk awaiting its indexes
        index: dict[int, NDArray[np.uint64]] | None = {}  # None: an index is unusable
        off = 8
        data_crc = zlib.crc32(MCAP_MAGIC)     # of bytes 0 .. off
        if size < off:
            self._stop(f"truncated at byte {size} of {size}: inside the opening magic")
            return
        while off < size:
            head = f.read(9) if off + 9 <= size else b""
            if len(head) < 9:
                self._stop(f"truncated at byte {off} of {size}: incomplete record header")
                break
            op, ln = _REC.unpack(head)
            start = off + 9
            end = start + ln
            name = _OP_NAMES.get(op, f"opcode 0x{op:02x}")
            body = f.read(ln) if end <= size else b""
            if len(body) < ln:               # past the end (or the file shrank meanwhile)
                self._stop(f"truncated at byte {off} of {size}: {name} record of {ln} bytes "
                           "runs past the end of the file")
                break
            if not self.accepted and op in (_OP_CHUNK, _OP_MESSAGE, _OP_CHANNEL):
                assert self.chain is not None
                self._refuse(self.chain.check_head(path, None))
                return
            crc_before, data_crc = data_crc, zlib.crc32(body, zlib.crc32(head, data_crc))
            try:
                if op == _OP_MESSAGE_INDEX:
                    if pending is not None and index is not None:
                        (cid,) = _U16.unpack_from(body, 0)
                        (nbytes,) = _U32.unpack_from(body, 2)
                        if 6 + nbytes > ln:   # no CRC on indexes: walk the chunk
                            index = None
                        else:
                            pairs = np.frombuffer(body, dtype="<u8", count=nbytes // 8,
                                                  offset=6)
                            index[cid] = pairs[1::2]
                    off = end
                    continue
                if pending is not None:       # the chunk's indexes are complete
                    self._chunk(pending, index)
                    pending = None
                if op == _OP_DATA_END:
                    self._data_end(f, size, body, crc_before, off, end)
                    return
                if op == _OP_CHUNK:
                    _, _, usize, crc = _CHUNK.unpack_from(body, 0)
                    compression, o = _str(body, 28)
                    (rlen,) = _U64.unpack_from(body, o)
                    raw = _decompress(compression, memoryview(body)[o + 8:o + 8 + rlen],
                                      usize)
                    if len(raw) != usize:
                        raise ValueError(f"decompressed {len(raw)} bytes, header says {usize}")
                    if crc and zlib.crc32(raw) != crc:
                        raise ValueError("CRC mismatch")
                    pending, index = raw, {}
                elif op == _OP_MESSAGE:
                    res.messages += self._walk(head + body)
                elif op == _OP_CHANNEL:
                    self._channel(body, 0)
                elif op == _OP_HEADER:
                    res.profile, o = _str(body, 0)
                    res.library, _ = _str(body, o)
                elif op == _OP_METADATA:
                    mname, o = _str(body, 0)
                    if not self._metadata(mname, _str_map(body, o)[0]):
                        return
                elif op == _OP_ATTACHMENT and self.first:
                    aname, o = _str(body, 16)
                    _, o = _str(body, o)
                    (dlen,) = _U64.unpack_from(body, o)
                    dend = o + 8 + dlen
                    if dend + 4 > ln:
                        raise ValueError("attachment data runs past its record")
                    (acrc,) = _U32.unpack_from(body, dend)
                    if acrc and zlib.crc32(memoryview(body)[:dend]) != acrc:
                        why = f"CRC mismatch in its Attachment record at byte {off}"
                        res.damaged_attachments[aname] = why
                        res.notes.append(f"attachment '{aname}' damaged ({why}): not used")
                    else:
                        res.attachments[aname] = body[o + 8:dend]
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
            except RecordingError:
                raise                 # a malformed payload (after_chunk, a handler)
            except Exception as exc:
                self._stop(f"corrupt chunk before byte {off} ({type(exc).__name__}: {exc})")

    def _data_end(self, f: BinaryIO, size: int, body: bytes, data_crc: int, off: int,
                  end: int) -> None:
        """At the DataEnd record at ``off`` (every chunk handed out): the data-section
        CRC (``data_crc``: of the bytes before it), then the Footer, its summary CRC and
        the closing magic (rig.recording.segments)."""
        (crc,) = _U32.unpack_from(body, 0)
        if crc and data_crc != crc:
            self._stop(f"data section damaged (CRC mismatch over bytes 0-{off}): the "
                       "chunks passed their own CRCs and were read, a record between them "
                       "(metadata, attachment, index) is damaged")
            return
        fd = f.fileno()
        tail = tail_problem(lambda o, n: os.pread(fd, n, o), size, end)
        if tail:
            self._stop(f"{tail}; every chunk before it was read")
            return
        self.footer = True

    def _stop(self, why: str) -> None:
        self.res.complete = False
        self.res.stopped_at = f"{self.path}: {why}"


def check_is_recording(res: ScanResult, path: Path, *, replayable: bool = True) -> None:
    """RecordingError unless ``res`` (the scan of ``path`` so far) is a recording of
    this software's format version, with its segment identity
    (:class:`rig.recording.segments.SegmentHead`), ``replayable``: with something to
    replay, on the channels of :data:`REQUIRED_TOPICS`.  Not ``replayable`` (:func:`read_run
    <rig.recording.run_data.read_run>`): a file cut anywhere is a prefix of a run, and
    a run without frames or events has no such channels."""
    meta = res.rig_metadata
    if not res.complete and not res.topics and not res.library and not meta:
        if not replayable:
            return
        raise RecordingError(f"{path}: nothing to replay: {res.stopped_at} "
                             "(cut inside the header)")
    if not res.library.startswith(RECORDER_LIBRARY_PREFIX) and not meta:
        raise RecordingError(
            f"{path}: foreign MCAP (profile {res.profile!r}, library {res.library!r}, "
            f"no '{METADATA_NAME}' metadata record; channels {sorted(res.topics) or 'none'})")
    # the version: of the metadata record, else (cut before it) of the writer's name
    version = meta.get("format_version", "(none)") if meta else \
        res.library[len(RECORDER_LIBRARY_PREFIX):]
    problem = version_problem(path, version)
    if problem:
        raise RecordingError(problem)
    if not res.topics and not res.complete and replayable:
        raise RecordingError(f"{path}: nothing to replay: {res.stopped_at} "
                             "(before the first complete chunk)")
    missing = [t for t in REQUIRED_TOPICS if t not in res.topics]
    if missing and replayable:
        raise RecordingError(f"{path}: missing channels {missing} (has "
                             f"{sorted(res.topics) or 'none'}; profile {res.profile!r}, "
                             f"library {res.library!r})")
    wrong = [t for t in REQUIRED_TOPICS if res.topics.get(t, MESSAGE_ENCODING)
             != MESSAGE_ENCODING]
    if wrong:
        raise RecordingError(f"{path}: channels {wrong} are not '{MESSAGE_ENCODING}' encoded")
    if meta and SegmentHead.parse(meta) is None:
        raise RecordingError(f"{path}: its '{METADATA_NAME}' metadata record has no segment "
                             "identity (run_id, segment, sequence_start), which every "
                             f"recording of format version {RECORDING_FORMAT_VERSION} has")


def scan_recording(path: str | Path, handlers: Mapping[str, Handler], *,
                   follow_segments: bool = True,
                   after_chunk: Callable[[], None] | None = None,
                   result: ScanResult | None = None, replayable: bool = True
                   ) -> ScanResult:
    """Scan a recording (and its rotation successors), calling ``handlers[topic]`` with
    each chunk's batch of that topic (see :data:`Handler`), in file order, and
    ``after_chunk()`` after each chunk.

    Raises :class:`RecordingError` (not an MCAP -- decided on the first 8 bytes --,
    foreign, another format version -- refused at its metadata record, before any data
    is handed out --, missing channels and nothing readable -- these two only if
    ``replayable``, see :func:`check_is_recording` --, a later segment of a run given
    instead of its first, a payload a handler or ``after_chunk`` cannot decode) and
    ``FileNotFoundError``.  A truncated or corrupt tail, a damaged summary or closing
    magic ends the scan after the last complete chunk (``complete`` False,
    ``stopped_at`` says where).  With ``follow_segments`` the next segment is the one
    the segment's end record names, and it is read only if it belongs to the run
    (:class:`rig.recording.segments.SegmentChain`); a missing or foreign segment ends the
    scan, ``stopped_at`` naming what is missing."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, expected a .mcap recording")
    res = result if result is not None else ScanResult()
    chain = SegmentChain(path) if follow_segments else None
    p: Path | None = path
    while p is not None:
        seg = _Segment(p, res, handlers, first=not res.segments, after_chunk=after_chunk,
                       chain=chain)
        res.segments.append(p)
        seg.scan()
        if seg.refused:
            res.segments.pop()
        if len(res.segments) == 1 and p == path:
            check_is_recording(res, p, replayable=replayable)
        p = next_segment(chain, p, seg.footer, seg.end, res)
    return res
