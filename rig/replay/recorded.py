"""What replay needs of a recording, decoded from the batches of the recording scanner
(:mod:`rig.recording.scan`).

:func:`load_recorded_run` returns a :class:`RecordedRun`: per-tick times, recorded
lateness / compute time and outputs (columns pulled out of the concatenated JSON with
one regex pass per topic, validated, with a per-message ``json`` fallback), the CAN
frames with their flags, the events and the recorded bus exceptions.  The decoding
goes piece by piece (:class:`RunDecoder`) so that a reader process
(:mod:`rig.replay.reader`) can hand pieces over while it reads on.
"""

from __future__ import annotations

import binascii
import itertools
import json
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from controller.artifact import Design, DesignMismatch, design_from_bytes
from controller.config import ConfigError, RigConfig, config_from_bytes
from rig.recording import schema
from rig.recording.scan import Handler, RecordingError, ScanResult, scan_recording, split_json
from rig.recording.schema import CONFIG_ATTACHMENT, DESIGN_ATTACHMENT
from rig.replay.bus_faults import BusFault, SendAttempts, bus_fault_of

__all__ = [
    "ERROR_FRAME",
    "EXTENDED_ID",
    "Piece",
    "RecordedRun",
    "RunDecoder",
    "RxFrame",
    "TxFrame",
    "as_piece",
    "assemble_run",
    "design_from_bytes",
    "load_recorded_run",
    "malformed_payload",
    "recorded_config",
    "recorded_design",
    "split_json",
]

#: frame flag bits of :data:`RxFrame` / :data:`TxFrame` (JSON keys ``error_frame`` /
#: ``extended_id``, present only when true)
ERROR_FRAME: Final = 1
EXTENDED_ID: Final = 2
#: (tick, t_ns, arbitration id, data, flags) of a received frame
RxFrame = tuple[int, int, int, bytes, int]
#: (tick, arbitration id, data, flags) of a sent frame
TxFrame = tuple[int, int, bytes, int]

_FRAME_RE: Final = re.compile(
    rb'\{"tick":(\d+),"t_ns":(-?\d+),"id":(\d+),"data":"([0-9a-f]*)","dlc":(\d+)\}')
_FLAGGED_FRAME_RE: Final = re.compile(
    rb'\{"tick":(\d+),"t_ns":(-?\d+),"id":(\d+),"data":"([0-9a-f]*)","dlc":(\d+)'
    rb'(,"error_frame":true)?(,"extended_id":true)?\}')


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
    rx: list[RxFrame]                  # (tick, t_ns, id, data, flags) in read order
    tx: list[TxFrame]                  # (tick, id, data, flags) in send order
    events: list[dict[str, Any]]       # {"tick", "t_ns", "kind", "detail"}
    first_internals: dict[str, Any] | None
    #: recorded recv / send exceptions in file order (also among ``events``)
    bus_faults: list[BusFault] = field(default_factory=list)

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


def _as_f64(a: NDArray[Any]) -> NDArray[np.float64]:
    """JSON numbers (:data:`~rig.recording.schema.NONFINITE_NUMBER` = NaN) -> float64
    (numpy parses like float())."""
    out = a.astype(np.float64)
    out[out == schema.NONFINITE_NUMBER] = np.nan
    return out


def _as_bool(a: NDArray[Any]) -> NDArray[np.int8]:
    return ((a == b"true") | (a == b"1")).astype(np.int8)


def _as_ns(a: NDArray[Any]) -> NDArray[np.int64]:
    """Seconds (as the loop wrote ``ns * 1e-9``) -> integer ns; not measured -> 0."""
    return np.nan_to_num(np.rint(_as_f64(a) * 1e9)).astype(np.int64)


def _frames(joined: bytes, n: int) -> list[RxFrame]:
    """(tick, t_ns, id, data, flags) of concatenated /can/rx or /can/tx messages."""
    if n == 0:
        return []
    flagged = b"true" in joined     # only a flag can say true (data are hex)
    found = (_FLAGGED_FRAME_RE if flagged else _FRAME_RE).findall(joined)
    flags: Any
    if len(found) == n:
        cols = np.array(found)
        tick, t_ns, fid = (cols[:, i].astype(np.int64).tolist() for i in range(3))
        data = list(map(binascii.unhexlify, cols[:, 3].tolist()))
        if flagged:
            flags = ((cols[:, 5] != b"") * ERROR_FRAME
                     | (cols[:, 6] != b"") * EXTENDED_ID).tolist()
        else:
            flags = itertools.repeat(0, n)
    else:
        decoded = split_json(joined)
        tick = [int(d["tick"]) for d in decoded]
        t_ns = [int(d["t_ns"]) for d in decoded]
        fid = [int(d["id"]) for d in decoded]
        data = [bytes.fromhex(d["data"]) for d in decoded]
        flags = [(ERROR_FRAME if d.get("error_frame") else 0)
                 | (EXTENDED_ID if d.get("extended_id") else 0) for d in decoded]
    return list(zip(tick, t_ns, fid, data, flags, strict=True))


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
class Piece:
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
    rx: list[RxFrame]
    tx: list[TxFrame]
    events: list[dict[str, Any]]
    bus_faults: list[BusFault]


def _concat(parts: list[NDArray[Any]], dtype: Any) -> NDArray[Any]:
    return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)


class RunDecoder:
    """Decodes a scan's batches piece by piece (a piece every ``flush_messages`` tick
    records): the working set stays small however long the recording is, and a reader
    process can hand pieces to the replay while it reads on (``emit``).

    A tick record's ``/rig/timing`` message (same MCAP sequence) may fall into the next
    chunk: trailing records whose timing has not been read yet are held back."""

    def __init__(self, flush_messages: int = 16384,
                 emit: Callable[[Piece], None] | None = None) -> None:
        self.flush_messages = flush_messages
        self.sig, self.tim, self.internals, self.rx, self.tx, self.events = (
            _Batches() for _ in range(6))
        self.pieces: list[Piece] = []
        self.emit = emit if emit is not None else self.pieces.append
        self.first: dict[str, Any] | None = None
        self._held: dict[str, NDArray[Any]] = {}
        self._held_seq = np.zeros(0, np.uint32)
        self._attempts = SendAttempts()

    def handlers(self) -> dict[str, Handler]:
        return {schema.TOPIC_SIGNALS: self.sig, schema.TOPIC_TIMING: self.tim,
                schema.TOPIC_INTERNALS: self._on_internals, schema.TOPIC_CAN_RX: self.rx,
                schema.TOPIC_CAN_TX: self.tx, schema.TOPIC_EVENTS: self.events}

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
        tx: list[TxFrame] = [(a, c, d, f) for a, _, c, d, f in
                             _frames(self.tx.joined(), self.tx.n)]
        events = [schema.event_from_message(m) for m in split_json(self.events.joined())]
        self.emit(Piece(
            tick=sig["tick"][:keep].astype(np.int64), t_ns=sig["t_ns"][:keep].astype(np.int64),
            lateness_ns=late[:keep], compute_ns=comp[:keep],
            spool_cmd=_as_f64(sig["spool_cmd"][:keep]),
            force_ref_n=_as_f64(sig["force_ref_n"][:keep]),
            valve_enable=_as_bool(sig["valve_enable"][:keep]),
            rx=_frames(self.rx.joined(), self.rx.n), tx=tx, events=events,
            bus_faults=self._bus_faults(events, tx)))
        for b in (self.sig, self.tim, self.rx, self.tx, self.events):
            b.clear()

    def _bus_faults(self, events: list[dict[str, Any]], tx: list[TxFrame]
                    ) -> list[BusFault]:
        """The piece's recorded bus exceptions, send failures numbered by attempt."""
        faults: list[BusFault] = []
        failed_sends: list[tuple[int, BusFault]] = []
        if any(e.get("kind") == "note" for e in events):
            ev_seq = self.events.sequence().tolist()
            for ev, seq in zip(events, ev_seq, strict=True):
                f = bus_fault_of(ev)
                if f is not None:
                    faults.append(f)
                    if f.where == "send":
                        failed_sends.append((seq, f))
        tx_seq = self.tx.sequence().tolist() if failed_sends else []
        numbered = iter(self._attempts.number(tx, tx_seq, failed_sends))
        return [next(numbered) if f.where == "send" else f for f in faults]


def assemble_run(path: Path, scan: ScanResult, pieces: Sequence[Piece],
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
        events=[e for p in pieces for e in p.events], first_internals=first,
        bus_faults=[f for p in pieces for f in p.bus_faults])


def as_piece(run: RecordedRun) -> Piece:
    return Piece(run.tick, run.t_ns, run.lateness_ns, run.compute_ns, run.spool_cmd,
                  run.force_ref_n, run.valve_enable, run.rx, run.tx, run.events,
                  run.bus_faults)


def malformed_payload(path: str | Path, exc: Exception) -> RecordingError:
    return RecordingError(f"{path}: malformed message payload ({type(exc).__name__}: "
                          f"{exc})")


def load_recorded_run(path: str | Path) -> RecordedRun:
    """Read what replay needs from a recording (see :func:`scan_recording` for errors)."""
    dec = RunDecoder()
    scan = scan_recording(path, dec.handlers(), after_chunk=dec.after_chunk)
    try:
        dec.flush(final=True)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise malformed_payload(path, exc) from exc
    return assemble_run(Path(path), scan, dec.pieces, dec.first)


def _attachment(run: RecordedRun, name: str, option: str) -> bytes:
    """The recording's attachment ``name``; its absence names the option that replaces it."""
    raw = run.scan.attachments.get(name)
    damage = run.scan.damaged_attachments.get(name)
    if damage:
        raise RecordingError(f"{run.path}: attachment '{name}' is damaged ({damage}); "
                             f"pass {option}")
    if raw is None:
        raise RecordingError(f"{run.path}: no '{name}' attachment; pass {option}")
    return raw


def recorded_config(run: RecordedRun) -> RigConfig:
    raw = _attachment(run, CONFIG_ATTACHMENT, "--config")
    try:
        return config_from_bytes(raw, f"{run.path}: attachment '{CONFIG_ATTACHMENT}'")
    except ConfigError as exc:
        raise RecordingError(f"{run.path}: attachment '{CONFIG_ATTACHMENT}': {exc}") from None


def recorded_design(run: RecordedRun) -> Design:
    raw = _attachment(run, DESIGN_ATTACHMENT, "--design")
    try:
        return design_from_bytes(raw)
    except DesignMismatch as exc:   # e.g. recorded with an older artifact version
        why = str(exc).split(": ", 1)[-1]
        raise RecordingError(f"{run.path}: the recorded design cannot be used ({why}); "
                             "pass --design") from exc


