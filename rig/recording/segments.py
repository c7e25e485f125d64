"""Segment sets and file integrity of recordings, for the one MCAP reader
(:func:`rig.recording.scan.scan_recording`, and so ``read_run``, replay and report).

A run is written as ``run.mcap``, ``run.001.mcap``, ... (``[recording] rotate_*``).  Each
segment opens with a ``rig`` metadata record that names its run and place
(:class:`SegmentHead`: ``run_id``, ``segment``, ``sequence_start``, ``first_tick``,
``first_segment``) and closes with a ``rig_segment_end`` metadata record
(:class:`SegmentEnd`: ``final`` or the ``next_segment`` file, ``sequence_end``,
``first_tick`` / ``last_tick``).  :class:`SegmentChain` follows a run from its first
segment: which file comes next, whether it is the right one (same run, next index,
sequence numbers continuing), and what exactly is missing when it is not.

:func:`tail_problem` checks the end of one MCAP file: the Footer record in place, its
summary CRC (it covers the summary section and the footer's own fields) and the
closing magic.  Format: ``docs/recording.md``.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Protocol

__all__ = [
    "MCAP_MAGIC",
    "SEGMENT_END_NAME",
    "ReadOutcome",
    "SegmentChain",
    "SegmentEnd",
    "SegmentHead",
    "base_of_segment",
    "next_segment",
    "segment_path",
    "tail_problem",
]

MCAP_MAGIC: Final = b"\x89MCAP0\r\n"
#: name of the metadata record that closes every segment
SEGMENT_END_NAME: Final = "rig_segment_end"
_FOOTER: Final = struct.Struct("<BQQQI")   # opcode, length, summary start, offsets, crc
_OP_FOOTER: Final = 0x02
_SEARCH_SLOTS: Final = 1000                 # how far past a gap later segments are looked for


def segment_path(base: Path, index: int) -> Path:
    """Segment ``index`` of the run whose first segment is ``base``."""
    return base if index == 0 else base.with_name(f"{base.stem}.{index:03d}.mcap")


def base_of_segment(path: Path) -> Path:
    """``run.003.mcap`` -> ``run.mcap`` (by name; a first segment is its own base)."""
    stem, dot, number = path.stem.rpartition(".")
    if dot and len(number) == 3 and number.isdigit():
        return path.with_name(f"{stem}.mcap")
    return path


def _int(meta: Mapping[str, str], key: str) -> int | None:
    try:
        return int(meta[key])
    except (KeyError, ValueError):
        return None


@dataclass(frozen=True)
class SegmentHead:
    """The identity of a segment (its ``rig`` metadata record)."""

    run_id: str
    index: int
    sequence_start: int           # MCAP sequence of the segment's first item
    first_tick: int | None        # tick of its first item (None for segment 0)
    first_segment: str           # file name of the run's first segment

    @classmethod
    def parse(cls, meta: Mapping[str, str] | None) -> SegmentHead | None:
        """None when ``meta`` does not identify a segment."""
        if meta is None or not meta.get("run_id"):
            return None
        index, seq = _int(meta, "segment"), _int(meta, "sequence_start")
        if index is None or index < 0 or seq is None:
            return None
        return cls(meta["run_id"], index, seq, _int(meta, "first_tick"),
                   meta.get("first_segment", ""))

    def describe(self) -> str:
        return f"segment {self.index} of run {self.run_id}"


@dataclass(frozen=True)
class SegmentEnd:
    """How a segment ended (its ``rig_segment_end`` metadata record)."""

    run_id: str
    index: int
    final: bool                   # the run ended with this segment
    next_segment: str             # file name of the next segment ('' when final)
    sequence_end: int             # one past the MCAP sequence of its last item
    first_tick: int | None        # ticks of its first and last item (None: no items)
    last_tick: int | None

    @classmethod
    def parse(cls, meta: Mapping[str, str] | None) -> SegmentEnd | None:
        if meta is None or not meta.get("run_id") or meta.get("final") not in ("true",
                                                                              "false"):
            return None
        index, seq = _int(meta, "segment"), _int(meta, "sequence_end")
        if index is None or seq is None:
            return None
        return cls(meta["run_id"], index, meta["final"] == "true",
                   meta.get("next_segment", ""), seq, _int(meta, "first_tick"),
                   _int(meta, "last_tick"))


def _ticks(a: int | None, b: int | None) -> str:
    if a is None or b is None:
        return "ticks unknown"
    return f"tick {a}" if a == b else f"ticks {a}-{b}"


class SegmentChain:
    """Follows the segments of one run from its first file.

    The caller reads a segment, then asks :meth:`check_head` (before using any of its
    data) and :meth:`next_path` (after reading it whole); both answer with what is
    wrong, in words that name the files, segments and ticks concerned."""

    def __init__(self, first: Path) -> None:
        self.first = first
        self.run_id = ""
        self.index = 0                 # segment expected next
        self.sequence = 0              # sequence the next segment must start at
        self.last_tick: int | None = None
        self.notes: list[str] = []     # harmless findings (e.g. a stale extra file)

    def check_first(self, head: SegmentHead | None) -> str:
        """'' when the first file read is segment 0 of a run, else why not (the file
        is a later segment: the run must be read from its first)."""
        if head is None:               # refused by rig.recording.scan.check_is_recording
            return ""
        if head.index != 0:
            start = base_of_segment(self.first)       # by name, else as recorded
            if not start.exists() and head.first_segment:
                start = self.first.with_name(head.first_segment)
            return (f"{self.first}: this is {head.describe()}; a run is read from its "
                    f"first segment: start from {start}")
        self.run_id = head.run_id
        self.sequence = head.sequence_start
        self.index = 1
        return ""

    def check_head(self, path: Path, head: SegmentHead | None) -> str:
        """'' when ``path`` is the expected next segment of this run, else why it is
        refused (nothing of it may be used)."""
        want = f"segment {self.index} of run {self.run_id}"
        after = self._after()
        if head is None:
            return (f"{path.name} is not {want}: it has no segment identity (a foreign "
                    f"file) -- not merged; {after}")
        if head.run_id != self.run_id or head.index != self.index:
            return (f"{path.name} is not {want}: it is {head.describe()} (foreign) -- "
                    f"not merged; {after}")
        if head.sequence_start != self.sequence:
            return (f"{path.name} ({want}) starts at item {head.sequence_start}, the run "
                    f"went on from item {self.sequence}: items are missing -- not "
                    f"merged; {after}")
        self.index += 1
        return ""

    def _after(self) -> str:
        where = f" (last tick {self.last_tick})" if self.last_tick is not None else ""
        return f"reading stopped after segment {self.index - 1}{where}"

    def next_path(self, path: Path, end: SegmentEnd | None) -> tuple[Path | None, str]:
        """After segment ``path`` was read whole: (next file to read, '') or (None, '')
        at the end of the run, or (None, what is missing)."""
        if end is None or end.run_id != self.run_id or end.index != self.index - 1:
            return None, (f"{path.name}: no end-of-segment record of segment "
                          f"{self.index - 1} of run {self.run_id}: cannot tell whether "
                          "the run goes on")
        if end.last_tick is not None:
            self.last_tick = end.last_tick
        self.sequence = end.sequence_end
        base = segment_path(self.first, 0)
        nxt = segment_path(base, self.index)
        if end.final:
            if nxt.exists():
                self.notes.append(f"{nxt.name} is not part of this recording (run "
                                  f"{self.run_id} ended with segment {self.index - 1}): "
                                  "ignored")
            return None, ""
        if nxt.exists():
            return nxt, ""
        recorded = path.with_name(end.next_segment) if end.next_segment else None
        if recorded is not None and recorded.exists():     # written under another name
            return recorded, ""
        return None, self._missing(base)

    def _missing(self, base: Path) -> str:
        """What is missing when the expected next segment does not exist."""
        k = self.index
        gone = segment_path(base, k).name
        last = self.last_tick
        for j in range(k + 1, k + 1 + _SEARCH_SLOTS):
            later = segment_path(base, j)
            if not later.exists():
                continue
            head = _peek_head(later)
            if head is None or head.run_id != self.run_id or head.index != j:
                continue
            names = gone if j == k + 1 else f"{gone} ... {segment_path(base, j - 1).name}"
            which = f"segment {k}" if j == k + 1 else f"segments {k}-{j - 1}"
            lost = _ticks(None if last is None else last + 1,
                          None if head.first_tick is None else head.first_tick - 1)
            return (f"{names} ({which} of run {self.run_id}) missing: {lost} are not in "
                    f"the recording; {later.name} and later segments were not read")
        after = f"after tick {last}" if last is not None else "after it"
        return (f"{gone} (segment {k} of run {self.run_id}) is missing: the run went on "
                f"{after} (from item {self.sequence}); nothing after segment {k - 1} "
                "was read")


def _peek_head(path: Path) -> SegmentHead | None:
    """The segment identity of ``path`` from its first records (a few kB at most)."""
    try:
        with open(path, "rb") as f:
            buf = f.read(1 << 16)
    except OSError:
        return None
    if buf[:8] != MCAP_MAGIC:
        return None
    off = 8
    rec = struct.Struct("<BQ")
    while off + 9 <= len(buf):
        op, ln = rec.unpack_from(buf, off)
        start, end = off + 9, off + 9 + ln
        if end > len(buf):
            return None
        if op == 0x0C:                   # Metadata
            try:
                name, meta = _metadata(buf, start)
            except (ValueError, struct.error, UnicodeDecodeError):
                return None
            if name == "rig":
                return SegmentHead.parse(meta)
        elif op not in (0x01, 0x09):     # Header, Attachment come before
            return None
        off = end
    return None


def _metadata(buf: bytes, off: int) -> tuple[str, dict[str, str]]:
    def text(o: int) -> tuple[str, int]:
        (n,) = struct.unpack_from("<I", buf, o)
        if o + 4 + n > len(buf):
            raise ValueError("string runs past the buffer")
        return buf[o + 4:o + 4 + n].decode("utf-8"), o + 4 + n

    name, off = text(off)
    (n,) = struct.unpack_from("<I", buf, off)
    off += 4
    end = off + n
    out: dict[str, str] = {}
    while off < end:
        k, off = text(off)
        v, off = text(off)
        out[k] = v
    return name, out


def tail_problem(read: Callable[[int, int], bytes], size: int,
                 summary_expected_at: int) -> str:
    """What is wrong with the end of an MCAP file of ``size`` bytes whose data section
    ends (DataEnd record included) at byte ``summary_expected_at``: '' when the Footer
    is in place, its summary CRC matches and the closing magic follows.

    ``read(offset, n) -> bytes`` reads the file (a buffer slice or a seek + read)."""
    tail_len = _FOOTER.size + len(MCAP_MAGIC)
    if size - summary_expected_at < tail_len:
        return (f"cut after the data section: {size - summary_expected_at} bytes follow "
                f"it, a Footer and the closing magic need {tail_len}")
    magic = read(size - 8, 8)
    if magic != MCAP_MAGIC:
        return f"closing magic missing or damaged (last 8 bytes {magic!r})"
    op, ln, summary_start, offsets_start, crc = _FOOTER.unpack(
        read(size - tail_len, _FOOTER.size))
    if op != _OP_FOOTER or ln != 20:
        return f"no Footer record before the closing magic (opcode 0x{op:02x})"
    footer_at = size - tail_len
    if summary_start and summary_start != summary_expected_at:
        return (f"Footer points at a summary section at byte {summary_start}, the data "
                f"section ends at byte {summary_expected_at}")
    if not summary_start and footer_at != summary_expected_at:
        return (f"{footer_at - summary_expected_at} bytes between the data section and "
                "a Footer that says there is no summary")
    if not summary_start <= offsets_start <= footer_at and offsets_start:
        return f"Footer's summary offsets start at byte {offsets_start}, outside the summary"
    if crc:
        first = summary_start or footer_at
        body = read(first, footer_at - first) + read(footer_at, _FOOTER.size - 4)
        if zlib.crc32(body) != crc:
            return (f"summary section or Footer damaged (CRC mismatch over bytes "
                    f"{first}-{footer_at + _FOOTER.size - 4})")
    return ""


class ReadOutcome(Protocol):
    """What a reader of a run reports besides the data (the scanner's result)."""

    complete: bool
    stopped_at: str | None
    notes: list[str]


def next_segment(chain: SegmentChain | None, path: Path, whole: bool,
                 end: Mapping[str, str] | None, outcome: ReadOutcome) -> Path | None:
    """The file to read after segment ``path`` (None: the run ends here).  A segment not
    read ``whole``, or no ``chain`` to follow, ends the run; a missing successor is
    recorded in ``outcome`` (incomplete, ``stopped_at``), and at the end of the run the
    chain's notes are added to it."""
    nxt: Path | None = None
    if whole and chain is not None and chain.run_id:
        nxt, problem = chain.next_path(path, SegmentEnd.parse(end))
        if problem:
            outcome.complete = False
            outcome.stopped_at = problem
    if nxt is None and chain is not None:
        outcome.notes.extend(chain.notes)
    return nxt
