"""The recording writer process: item stream on stdin -> MCAP files.

Started by :class:`rig.recording.recorder.RunRecorder` as ``python -m rig.recording.writer``; never
run by hand.  It reads the stream of :mod:`rig.recording.codec` from stdin, encodes JSON,
fills MCAP chunks, flushes every finished chunk to the OS and rotates segments.  All of
this used to run on a thread of the control loop's process, where it held the GIL for
tens of microseconds at a time and delayed the loop's wake-ups; in its own process it
cannot.

Two threads: a reader drains the pipe into a backlog of at most ``queue_size`` items
(then it stops reading, the pipe fills and the loop side drops and counts), and the
writer encodes.  Status goes to stdout as JSON lines (``ready``, ``progress`` about
every second, ``error``, ``final``).  SIGINT and SIGTERM are ignored: the writer ends
when the loop closes the stream (an END item) or dies (end of file); either way the
backlog is written and the segment gets its summary and footer.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from rig.recording import schema
from rig.recording.codec import (
    FRAME_ERROR,
    FRAME_EXTENDED,
    FRAME_RX,
    STREAM_MAGIC,
    TickDecoder,
    decode_item,
    iter_items,
    read_exact,
    read_stream_header,
    split_items,
)
from rig.recording.cpus import leave_the_loops_cpus
from rig.recording.scene import next_scene_ns, scene_json
from rig.recording.schema import (
    CONFIG_ATTACHMENT,
    DESIGN_ATTACHMENT,
    MESSAGE_ENCODING,
    METADATA_NAME,
    RECORDING_FORMAT_VERSION,
    SCHEMA_ENCODING,
    TOPICS,
    encode_message,
    event_from_message,
    event_message,
    log_message,
    schema_bytes,
    split_record,
)
from rig.recording.segments import SEGMENT_END_NAME, segment_path

__all__ = ["CONFIG_ATTACHMENT", "DESIGN_ATTACHMENT", "METADATA_NAME", "McapRunSink",
           "ParentLines", "main", "segment_path", "stay_out_of_the_loops_way"]

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}


class McapRunSink:
    """Decoded items -> MCAP segments (rotation by size / time, chunk flushing)."""

    def __init__(self, base: Path, *, rotate_bytes: int, rotate_seconds: float,
                 chunk_bytes: int, compression: str, clock_offset_ns: int,
                 metadata: Mapping[str, str], config_toml: str, design: bytes | None,
                 max_chunk_age_s: float) -> None:
        self.base = base
        self.paths: list[Path] = []
        self._rotate_bytes = rotate_bytes
        self._rotate_ns = int(rotate_seconds * 1e9)
        self._chunk_bytes = chunk_bytes
        self._compression = _COMPRESSION[compression]
        self._offset = clock_offset_ns
        self._meta = dict(metadata)
        self._config_toml = config_toml
        self._design = design
        self._max_chunk_age_s = max_chunk_age_s
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._seg_t0: int | None = None
        self._next_scene_ns: int | None = None    # loop time of the next picture
        self._seq = 0
        self._seg_seq0 = 0                       # sequence of the segment's first item
        self._seg_ticks: list[int] = []          # [first, last] tick of the segment
        self._n_since_size_check = 0
        self.written = 0
        self.malformed = 0
        self.last_malformed: str | None = None
        self._open_segment()

    # ------------------------------------------------------------------ segments
    def _open_segment(self, first_tick: int | None = None) -> None:
        """Start segment ``len(paths)``; its ``rig`` metadata names the run, the segment
        index, the sequence number and tick of its first item (rig.recording.segments)."""
        path = segment_path(self.base, len(self.paths))
        stream = open(path, "wb")  # noqa: SIM115 (closed in finish_segment)
        # enable_data_crcs: the DataEnd record carries the CRC of the whole data section
        # (metadata and index records have no CRC of their own)
        writer = Writer(stream, chunk_size=self._chunk_bytes, compression=self._compression,
                        enable_data_crcs=True)
        writer.start(profile="", library=f"rig-recorder/{RECORDING_FORMAT_VERSION}")
        now = time.time_ns()
        self._seg_seq0 = self._seq
        self._seg_ticks = []
        writer.add_metadata(METADATA_NAME, {
            **self._meta, "segment": str(len(self.paths)), "first_segment": self.base.name,
            "sequence_start": str(self._seq),
            "first_tick": "" if first_tick is None else str(first_tick)})
        writer.add_attachment(now, now, CONFIG_ATTACHMENT, "application/toml",
                              self._config_toml.encode())
        if self._design is not None:
            writer.add_attachment(now, now, DESIGN_ATTACHMENT, "application/octet-stream",
                                  self._design)
        self._channels = {}
        for topic, topic_schema in TOPICS.items():
            sid = writer.register_schema(topic_schema["title"], SCHEMA_ENCODING,
                                         schema_bytes(topic_schema))
            self._channels[topic] = writer.register_channel(topic, MESSAGE_ENCODING, sid)
        stream.flush()
        self.paths.append(path)
        self._stream, self._writer = stream, writer
        self._seg_t0 = None
        self._last_size = stream.tell()
        self._last_chunk_mono = time.monotonic()

    def _finalize_chunk(self) -> None:
        # mcap.Writer has no public "close the open chunk"; 1.x names it like this.
        finalize = getattr(self._writer, "_Writer__finalize_chunk", None)
        if finalize is not None:
            finalize()

    def finish_segment(self, final: bool = True) -> None:
        """Close the segment: its last chunk, the ``rig_segment_end`` record (``final``
        or the next segment's file name, the sequence after its last item, its first and
        last tick), summary and footer."""
        if self._writer is not None and self._stream is not None:
            self._finalize_chunk()      # the end record comes after every message
            ticks = self._seg_ticks
            self._writer.add_metadata(SEGMENT_END_NAME, {
                "run_id": str(self._meta.get("run_id", "")),
                "segment": str(len(self.paths) - 1),
                "final": "true" if final else "false",
                "next_segment": "" if final else segment_path(self.base, len(self.paths)).name,
                "sequence_end": str(self._seq),
                "items": str(self._seq - self._seg_seq0),
                "first_tick": str(ticks[0]) if ticks else "",
                "last_tick": str(ticks[-1]) if ticks else ""})
            self._writer.finish()
            self._stream.close()
        self._writer = self._stream = None

    def _maybe_rotate(self, item: tuple[Any, ...]) -> None:
        t_ns = int(item[1])
        if self._seg_t0 is None:
            self._seg_t0 = t_ns
            return
        assert self._stream is not None
        self._n_since_size_check += 1
        check_size = self._n_since_size_check >= 64
        if check_size:
            self._n_since_size_check = 0
        if (t_ns - self._seg_t0 >= self._rotate_ns
                or (check_size and self._stream.tell() >= self._rotate_bytes)):
            self.finish_segment(final=False)
            self._open_segment(_item_tick(item))
            self._seg_t0 = t_ns

    def flush(self) -> None:
        """Push finished chunks to the OS; close a chunk older than max_chunk_age_s."""
        assert self._stream is not None
        now = time.monotonic()
        size = self._stream.tell()
        if size != self._last_size:
            self._last_size = size
            self._last_chunk_mono = now
        elif now - self._last_chunk_mono > self._max_chunk_age_s:
            self._finalize_chunk()
            self._last_chunk_mono = now
            self._last_size = self._stream.tell()
        self._stream.flush()

    # ------------------------------------------------------------------ items
    def write(self, item: tuple[Any, ...]) -> None:
        """Write one decoded item; a malformed one is skipped and counted."""
        try:
            self._maybe_rotate(item)
            self._write(item)
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            self.malformed += 1
            self.last_malformed = f"{type(exc).__name__}: {exc} in {item[:3]!r}"

    def _write(self, item: tuple[Any, ...]) -> None:
        w = self._writer
        assert w is not None
        seq = self._seq & 0xFFFFFFFF
        kind = item[0]
        t_ns = int(item[1])
        log_time = max(t_ns + self._offset, 0)
        if kind == "frame":
            _, _, tick, arb, data, flags = item
            extra = b""
            if flags & FRAME_ERROR:
                extra += b',"error_frame":true'
            if flags & FRAME_EXTENDED:
                extra += b',"extended_id":true'
            payload = b'{"tick":%d,"t_ns":%d,"id":%d,"data":"%s","dlc":%d%s}' % (
                tick, t_ns, arb, data.hex().encode(), len(data), extra)
            ch = self._channels[schema.TOPIC_CAN_RX if flags & FRAME_RX else schema.TOPIC_CAN_TX]
            w.add_message(ch, log_time, payload, log_time, seq)
        elif kind == "tick":
            record: Mapping[str, Any] = item[2]
            encoded = [(topic, encode_message(msg))
                       for topic, msg in split_record(t_ns, record)]
            for topic, blob in encoded:
                w.add_message(self._channels[topic], log_time, blob, log_time, seq)
            if self._next_scene_ns is None or t_ns >= self._next_scene_ns:
                self._next_scene_ns = next_scene_ns(self._next_scene_ns, t_ns)
                tf, scene = scene_json(log_time, record.get("rattlespace_m"),
                                       record.get("force_meas_n"),
                                       str(record.get("lifecycle", "")))
                w.add_message(self._channels[schema.TOPIC_TF], log_time, tf, log_time, seq)
                w.add_message(self._channels[schema.TOPIC_SCENE], log_time, scene, log_time,
                              seq)
        elif kind == "event":
            _, _, tick, kind_s, detail = item
            msg = event_message(t_ns, tick, kind_s, detail)
            w.add_message(self._channels[schema.TOPIC_EVENTS], log_time, encode_message(msg),
                          log_time, seq)
            w.add_message(self._channels[schema.TOPIC_LOG], log_time,
                          encode_message(log_message(log_time, int(tick), msg["kind"],
                                                     event_from_message(msg)["detail"])),
                          log_time, seq)
        else:
            raise ValueError(f"unknown item {kind!r}")
        self._seq += 1
        self.written += 1
        tick = _item_tick(item)
        if tick is not None:
            ticks = self._seg_ticks
            if ticks:
                ticks[-1] = tick
            else:
                ticks[:] = [tick, tick]


def _item_tick(item: tuple[Any, ...]) -> int | None:
    """The loop tick of a decoded item (None when it has none)."""
    try:
        if item[0] == "tick":
            return int(item[2]["tick"])
        if item[0] in ("frame", "event"):
            return int(item[2])
    except (KeyError, TypeError, ValueError, IndexError):
        return None
    return None


# ---------------------------------------------------------------------------- process


class ParentLines:
    """JSON lines to the parent process on stdout (``{"event": ..., **fields}``), from any
    thread: the recorder's writer's status and the telemetry process's events and
    commands.  A broken pipe (the parent is gone) silences it; the child goes on."""

    def __init__(self, out: IO[str]) -> None:
        self.out = out
        self.lock = threading.Lock()
        self.broken = False

    def send(self, event: str, **fields: Any) -> bool:
        line = json.dumps({"event": event, **fields}, default=str) + "\n"
        with self.lock:
            if self.broken:
                return False
            try:
                self.out.write(line)
                self.out.flush()
            except (BrokenPipeError, OSError, ValueError):
                self.broken = True
                return False
        return True


class _Backlog:
    """Reader thread: pipe -> complete items, at most ``limit`` items waiting."""

    def __init__(self, fd: int, limit: int) -> None:
        self.fd = fd
        self.limit = max(1, limit)
        self.chunks: collections.deque[tuple[bytes, int]] = collections.deque()
        self.items = 0
        self.eof = False
        self.error: str | None = None
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._run, name="record-reader", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        carry = b""
        try:
            while True:
                with self.cond:
                    while self.items >= self.limit:
                        self.cond.wait(0.05)
                data = os.read(self.fd, 1 << 18)
                if not data:
                    if carry:
                        self.error = f"stream ended inside an item ({len(carry)} bytes lost)"
                    break
                buf = carry + data if carry else data
                end, count = split_items(buf)
                carry = buf[end:]
                if count:
                    with self.cond:
                        self.chunks.append((buf[:end], count))
                        self.items += count
                        self.cond.notify_all()
        except (OSError, ValueError) as exc:
            self.error = f"reading the item stream: {exc}"
        with self.cond:
            self.eof = True
            self.cond.notify_all()

    def take(self, timeout_s: float) -> tuple[bytes, int] | None:
        with self.cond:
            if not self.chunks and not self.eof:
                self.cond.wait(timeout_s)
            if not self.chunks:
                return None
            chunk = self.chunks.popleft()
            self.items -= chunk[1]
            self.cond.notify_all()
            return chunk


def stay_out_of_the_loops_way() -> None:
    """Ignore the stop signals (the loop process ends the writer; the telemetry process
    too, rig.telemetry_process.child), drop a real-time
    policy inherited from the loop, and leave the loop's CPUs when it is pinned to some
    (systemd ``CPUAffinity=``) and others exist."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(os, "sched_setscheduler"):
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    leave_the_loops_cpus()


def main() -> int:
    stay_out_of_the_loops_way()
    status = ParentLines(sys.stdout)
    fd = sys.stdin.fileno()
    try:
        header = read_stream_header(fd, STREAM_MAGIC, "recording stream")
        (dlen,) = struct.unpack("<I", read_exact(fd, 4, "recording stream"))
        design = read_exact(fd, dlen, "recording stream") if dlen else None
        ticks: TickDecoder | None = None
        sink = McapRunSink(
            Path(header["path"]), rotate_bytes=int(header["rotate_bytes"]),
            rotate_seconds=float(header["rotate_seconds"]),
            chunk_bytes=int(header["chunk_bytes"]), compression=header["compression"],
            clock_offset_ns=int(header["clock_offset_ns"]), metadata=header["metadata"],
            config_toml=header["config_toml"], design=design,
            max_chunk_age_s=float(header["max_chunk_age_s"]))
    except (OSError, ValueError, KeyError, EOFError) as exc:
        status.send("error", error=f"{type(exc).__name__}: {exc}")
        return 1
    status.send("ready", paths=[str(p) for p in sink.paths])
    poll_s = float(header.get("poll_s", 0.002))
    backlog = _Backlog(fd, int(header["queue_size"]))
    clean_end = False
    error: str | None = None
    last_status = 0.0

    def progress(event: str = "progress") -> None:
        status.send(event, written=sink.written, malformed=sink.malformed,
                    last_malformed=sink.last_malformed, paths=[str(p) for p in sink.paths],
                    error=error, clean_end=clean_end)

    try:
        while True:
            got = backlog.take(poll_s)
            if got is not None:
                for raw in iter_items(got[0]):
                    try:
                        item = decode_item(raw, ticks)
                    except Exception as exc:  # undecodable item: skip, count
                        sink.malformed += 1
                        sink.last_malformed = f"{type(exc).__name__}: {exc}"
                        continue
                    if item[0] == "end":
                        clean_end = True
                        continue
                    if item[0] == "layout":
                        ticks = TickDecoder(item[1])
                        continue
                    sink.write(item)
            elif backlog.eof:
                break
            sink.flush()
            now = time.monotonic()
            if now - last_status > 1.0:   # each line costs the loop process a parse
                last_status = now
                progress()
    except OSError as exc:
        error = f"recording to {sink.paths[-1]} failed: {exc}"
    try:
        sink.finish_segment()
    except OSError as exc:
        error = error or f"closing {sink.paths[-1]}: {exc}"
    if backlog.error and not clean_end:
        error = error or backlog.error
    if not clean_end and error is None:
        print(f"rig.recording.writer: the loop process ended without closing {sink.base}; "
              f"everything it sent is written", file=sys.stderr)
    progress("final")
    return 0 if error is None else 1


if __name__ == "__main__":
    sys.exit(main())
