"""A recording as Python objects: every CAN frame, tick record and event of a run.

:func:`read_run` is the Python API of recordings (tests, notebooks, one-off analyses).
It is built on the one MCAP reader, :func:`rig.recording.scan.scan_recording` (the
scanner replay and the report use): the scanner walks the files, checks the format
version, the segment chain and the file integrity and hands out the JSON payloads of
each chunk per topic; this module turns them into :class:`CanFrameRecord`,
:class:`TickRecord` and :class:`EventRecord` objects.

Order: the writer gives every item (frame, tick record, event) one MCAP ``sequence``
number, in the order it writes them, across segments (``docs/recording.md``); a tick
record's messages (``/rig/signals``, ``/controller/internals``, ``/rig/timing``) share
their item's number and are merged back by it.  The items' ``index`` is their rank in
that order.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from rig.recording.scan import RecordingError, ScanResult, scan_recording, split_json
from rig.recording.schema import (
    NONFINITE_NUMBER,
    PARTS_KEY,
    TOPIC_CAN_RX,
    TOPIC_CAN_TX,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_SIGNALS,
    TOPIC_TIMING,
    event_from_message,
)

__all__ = ["STREAM_BATCH_TICKS", "CanFrameRecord", "EventRecord", "RunData", "TickRecord",
           "read_run", "stream_run"]

#: the messages of a tick record, in the order the writer writes them (signals first,
#: carrying PARTS_KEY)
_RECORD_TOPICS: Final = (TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_TIMING)
_TOPICS: Final = (*_RECORD_TOPICS, TOPIC_CAN_RX, TOPIC_CAN_TX, TOPIC_EVENTS)
_WRAP: Final = 1 << 32          # MCAP sequence numbers are u32


@dataclass(frozen=True)
class CanFrameRecord:
    index: int            # position in the run (recording order across segments)
    t_ns: int
    tick: int
    arbitration_id: int
    data: bytes
    is_rx: bool
    is_error_frame: bool = False
    is_extended_id: bool = False


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
    complete: bool = True          # every segment present, intact, with its footer
    stopped_at: str | None = None  # where and why reading stopped early
    notes: list[str] = field(default_factory=list)  # e.g. a stale file after the run

    def timeline(self) -> Iterator[CanFrameRecord | TickRecord | EventRecord]:
        """Frames, records and events merged in recording order."""
        items: list[CanFrameRecord | TickRecord | EventRecord] = [
            *self.frames, *self.records, *self.events]
        return iter(sorted(items, key=lambda r: r.index))


class _Sequences:
    """Unwraps the u32 MCAP sequence numbers of the batches (in file order) into
    int64 item numbers."""

    def __init__(self) -> None:
        self.last: int | None = None

    def unwrap(self, seqs: NDArray[np.uint32]) -> NDArray[np.int64]:
        u = seqs.astype(np.int64)
        if not u.size:
            return u
        if self.last is None:
            self.last = int(u[0])
        u += self.last - self.last % _WRAP
        u[u < self.last - _WRAP // 2] += _WRAP
        u[u > self.last + _WRAP // 2] -= _WRAP
        self.last = max(self.last, int(u.max()))
        return u


class _Topic:
    """The messages of one topic as they are read (a scanner handler): decoded JSON
    objects and their item numbers."""

    def __init__(self, topic: str, scan: ScanResult, sequences: _Sequences) -> None:
        self.topic, self._scan, self._sequences = topic, scan, sequences
        self.msgs: list[dict[str, Any]] = []
        self.seqs: list[NDArray[np.int64]] = []

    def __call__(self, joined: bytes, seqs: NDArray[np.uint32]) -> None:
        try:
            msgs = split_json(joined)
        except ValueError as exc:              # JSONDecodeError, UnicodeDecodeError
            msgs, why = [], f"({type(exc).__name__}: {str(exc)[:120]})"
        else:
            why = "(not one JSON object per message)"
        if len(msgs) != seqs.size or not all(type(m) is dict for m in msgs):
            raise RecordingError(f"{self._scan.segments[-1]}: malformed {self.topic} "
                                 f"payload {why}")
        self.msgs += msgs
        self.seqs.append(self._sequences.unwrap(seqs))

    def sequence(self) -> NDArray[np.int64]:
        return np.concatenate(self.seqs) if self.seqs else np.zeros(0, np.int64)


def read_run(path: str | Path, *, follow_segments: bool = True) -> RunData:
    """Read a recording (and its rotation successors).  A truncated file (no footer,
    partial chunk) yields everything up to the last complete chunk -- a file cut
    anywhere, even inside its header, reads as a prefix of the run --; ``complete`` is
    False and ``stopped_at`` says where and why reading stopped.  A tick record cut
    between its messages by a crash is dropped whole (``stopped_at`` says so).

    With ``follow_segments`` the run is read from its first segment on, segment by
    segment as each one's end record names the next, and a segment is used only when it
    belongs (same run id, next index, sequence numbers continuing,
    :mod:`rig.recording.segments`).  Reading stops at the first incomplete, damaged,
    missing or foreign segment, and ``stopped_at`` says which and what is missing.

    Raises :class:`rig.recording.scan.RecordingError` (a ``ValueError``) when ``path``
    is a later segment of its run (read from the first), not an MCAP file, a foreign
    MCAP, a recording of another format version, or holds a payload that is not the
    format's JSON; ``FileNotFoundError`` / ``IsADirectoryError``."""
    path = Path(path)
    scan = ScanResult()
    sequences = _Sequences()
    topics = {t: _Topic(t, scan, sequences) for t in _TOPICS}
    with _collector_paused():
        scan_recording(path, dict(topics), follow_segments=follow_segments, result=scan,
                       replayable=False)
        run = RunData(metadata=scan.metadata, attachments=scan.attachments,
                      segments=scan.segments, complete=scan.complete,
                      stopped_at=scan.stopped_at, notes=scan.notes)
        try:
            _decode(topics, run)
        except (KeyError, TypeError, AttributeError, ValueError) as exc:  # a missing key
            raise RecordingError(f"{path}: malformed message payload "
                                 f"({type(exc).__name__}: {exc})") from exc
    return run


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """The cyclic garbage collector off while the run's objects are built (none of them
    forms a cycle; every generation-0 pass would rescan the growing lists: a third of
    the reading time), back to its previous state afterwards."""
    was_on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_on:
            gc.enable()


def _decode(topics: dict[str, _Topic], run: RunData) -> None:
    records = _records(topics)
    if not run.complete and records:           # a crash can cut the last record
        last = max(records)
        data, expected, seen = records[last]
        if seen < expected:
            del records[last]
            run.stopped_at = (f"{run.stopped_at}; dropped torn record of tick "
                              f"{data['tick']} ({seen}/{expected} parts)")
    rec_q = np.fromiter(sorted(records), np.int64, len(records))
    rx, tx, events = (topics[t] for t in (TOPIC_CAN_RX, TOPIC_CAN_TX, TOPIC_EVENTS))
    # index = rank in item order; a record before a frame or event of its number
    every = np.concatenate((rec_q, rx.sequence(), tx.sequence(), events.sequence()))
    rank = np.concatenate((np.zeros(rec_q.size, np.int8), np.ones(every.size - rec_q.size,
                                                                  np.int8)))
    index = np.empty(every.size, np.int64)
    index[np.lexsort((rank, every))] = np.arange(every.size)
    at = np.cumsum([0, rec_q.size, len(rx.msgs), len(tx.msgs)]).tolist()
    idx = index.tolist()
    tick_records = []
    for i, q in zip(idx[:at[1]], rec_q.tolist(), strict=True):
        tick_records.append(_tick_record(i, records[q][0]))
    run.records = tick_records
    frames = [_frame(i, m, True) for i, m in zip(idx[at[1]:at[2]], rx.msgs, strict=True)]
    frames += [_frame(i, m, False) for i, m in zip(idx[at[2]:at[3]], tx.msgs, strict=True)]
    frames.sort(key=lambda f: f.index)
    run.frames = frames
    run.events = [EventRecord(i, e["t_ns"], e["tick"], e["kind"], e["detail"])
                  for i, e in zip(idx[at[3]:], map(event_from_message, events.msgs),
                                  strict=True)]


def _tick_record(index: int, data: dict[str, Any]) -> TickRecord:
    """The merged messages of a tick record as a :class:`TickRecord`."""
    for key in data.get("nonfinite", ()):
        data[key] = _none_for_nonfinite(data.get(key))
    return TickRecord(index, data.pop("t_ns"), data["tick"], data)


def _none_for_nonfinite(value: Any) -> Any:
    """:data:`NONFINITE_NUMBER` (in a key listed in ``nonfinite``) -> None, in lists too."""
    if isinstance(value, list):
        return [_none_for_nonfinite(v) for v in value]
    return None if value == NONFINITE_NUMBER else value


def _records(topics: dict[str, _Topic],
             records: dict[int, list[Any]] | None = None) -> dict[int, list[Any]]:
    """Tick records by item number: [merged data, messages expected, messages read]
    (merged into ``records``, the records still open, when given)."""
    records = {} if records is None else records
    for topic in _RECORD_TOPICS:
        part = topics[topic]
        for q, msg in zip(part.sequence().tolist(), part.msgs, strict=True):
            rec = records.get(q)
            if rec is None:
                records[q] = [msg, int(msg.pop(PARTS_KEY, 1)), 1]
                continue
            data = rec[0]
            bad = data.get("nonfinite", []) + msg.get("nonfinite", [])
            data.update(msg)
            if bad:
                data["nonfinite"] = bad
            rec[2] += 1
    return records


def _frame(index: int, msg: dict[str, Any], is_rx: bool) -> CanFrameRecord:
    return CanFrameRecord(index, msg["t_ns"], msg["tick"], msg["id"],
                          bytes.fromhex(msg["data"]), is_rx,
                          bool(msg.get("error_frame", False)),
                          bool(msg.get("extended_id", False)))


#: default batch of :func:`stream_run`: 10 s of ticks at 1 kHz
STREAM_BATCH_TICKS: Final = 10_000


def stream_run(path: str | Path, on_batch: Callable[[RunData], None], *,
               batch_ticks: int = STREAM_BATCH_TICKS, follow_segments: bool = True
               ) -> RunData:
    """Read a recording as :func:`read_run` does, handing out the tick records and
    frames in batches of at least ``batch_ticks`` records (at chunk boundaries), in
    recording order, decoded by the same code: the concatenation of the batches'
    ``records`` / ``frames`` is ``read_run``'s, except that ``index`` is the item's
    MCAP sequence number (unwrapped), not its rank.  Events are not read.  Memory:
    one batch plus one chunk, whatever the length of the run.

    Returns the run's metadata, segments, ``complete``, ``stopped_at`` (no items).
    Raises as :func:`read_run`."""
    path = Path(path)
    scan = ScanResult()
    sequences = _Sequences()
    topics = {t: _Topic(t, scan, sequences) for t in _TOPICS if t != TOPIC_EVENTS}
    batch = _Batch(topics, on_batch, scan)

    def after_chunk() -> None:
        batch.take()
        if batch.ready(batch_ticks):
            batch.flush(final=False)

    with _collector_paused():
        scan_recording(path, dict(topics), follow_segments=follow_segments, result=scan,
                       after_chunk=after_chunk, replayable=False)
        batch.take()
        run = RunData(metadata=scan.metadata, attachments=scan.attachments,
                      segments=scan.segments, complete=scan.complete,
                      stopped_at=scan.stopped_at, notes=scan.notes)
        try:
            dropped = batch.flush(final=True)
        except (KeyError, TypeError, AttributeError, ValueError) as exc:
            raise RecordingError(f"{path}: malformed message payload "
                                 f"({type(exc).__name__}: {exc})") from exc
    if dropped:
        run.stopped_at = f"{run.stopped_at}; {dropped}"
    return run


class _Batch:
    """The open tick records and the frames read since the last batch."""

    def __init__(self, topics: dict[str, _Topic], on_batch: Callable[[RunData], None],
                 scan: ScanResult) -> None:
        self.topics, self.on_batch, self.scan = topics, on_batch, scan
        self.records: dict[int, list[Any]] = {}
        self.frames: list[CanFrameRecord] = []

    def take(self) -> None:
        """Move the topics' messages (one chunk) into the batch."""
        _records(self.topics, self.records)
        for topic, is_rx in ((TOPIC_CAN_RX, True), (TOPIC_CAN_TX, False)):
            part = self.topics[topic]
            self.frames += [_frame(q, m, is_rx) for q, m in
                            zip(part.sequence().tolist(), part.msgs, strict=True)]
        for part in self.topics.values():
            part.msgs, part.seqs = [], []

    def ready(self, batch_ticks: int) -> bool:
        return len(self.records) > batch_ticks

    def flush(self, *, final: bool) -> str:
        """Hand out the records (all but the last one, which the next chunk may
        continue, unless ``final``) and the frames; returns the note on a torn last
        record dropped (a recording cut by a crash), else ''."""
        dropped = ""
        keep = sorted(self.records)
        if not final and keep:
            keep = keep[:-1]
        elif keep and not self.scan.complete:
            data, expected, seen = self.records[keep[-1]]
            if seen < expected:
                del self.records[keep.pop()]
                dropped = (f"dropped torn record of tick {data['tick']} "
                           f"({seen}/{expected} parts)")
        records = [_tick_record(q, self.records.pop(q)[0]) for q in keep]
        self.frames.sort(key=lambda f: f.index)
        frames, self.frames = self.frames, []
        if records or frames:
            self.on_batch(RunData(frames=frames, records=records,
                                  metadata=self.scan.metadata, segments=self.scan.segments))
        return dropped
