"""Recorded bus exceptions: what replay raises again where the recorded bus raised.

When ``bus.recv`` raises (``can.CanError`` / ``OSError``) the loop records a ``note``
event ``{"bus_exception": "recv", "type", "error", "errno"}`` at that tick and stops
draining; when ``bus.send`` fails, ``{"bus_exception": "send", ..., "arbitration_id"}``
and the frame is missing from ``/can/tx`` (``rig.service.loop._bus_exception``).  The loop's
fault classification (``rig.bus.core.classify_bus_exception``) looks only at the errno, so
an exception rebuilt from the type name, message and errno (:meth:`BusFault.exception`)
gives the same BUS_ERROR / BUS_OFF.

A send failure is pinned to its *attempt*: the how-many-th send of that frame ID in the
tick it was (a FaultReport goes out twice in a tick when a fault latches on a heartbeat
tick).  The attempt comes from the file order of ``/can/tx`` frames and the note
events (their MCAP sequence numbers), counted across decoding pieces by
:class:`SendAttempts`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final

import can

__all__ = ["BusFault", "SendAttempts", "bus_fault_of"]

#: exception types rebuilt by name (others become ``can.CanOperationError``)
_CAN_TYPES: Final[dict[str, type[can.CanError]]] = {
    c.__name__: c for c in (can.CanError, can.CanOperationError, can.CanTimeoutError,
                            can.CanInitializationError)}
_OS_TYPES: Final[dict[str, type[OSError]]] = {
    c.__name__: c for c in (OSError, BlockingIOError, BrokenPipeError, ConnectionError,
                            ConnectionResetError, InterruptedError, PermissionError,
                            TimeoutError)}


@dataclass(frozen=True)
class BusFault:
    """One recorded bus exception: ``recv`` raised in ``tick``, or the ``attempt``-th
    send (from 0; None = unknown: the first send not yet failed) of ``arbitration_id``
    in ``tick`` failed."""

    tick: int
    where: str                   # "recv" or "send"
    type_name: str               # class name of the recorded exception
    error: str                   # its str()
    errno: int | None
    arbitration_id: int | None = None
    attempt: int | None = None

    def exception(self) -> Exception:
        """An exception the loop classifies as it did the recorded one (same errno;
        the same class when it is a python-can or an OS error class)."""
        errno = self.errno
        os_type = _OS_TYPES.get(self.type_name)
        if os_type is not None:
            if errno is None:
                return os_type(self.error)
            return os_type(errno, self.error.removeprefix(f"[Errno {errno}] "))
        can_type = _CAN_TYPES.get(self.type_name, can.CanOperationError)
        message = self.error
        if errno is not None:   # CanError appends " [Error Code N]" itself
            message = message.removesuffix(f" [Error Code {errno}]")
        return can_type(message, error_code=errno)


def bus_fault_of(event: Mapping[str, Any]) -> BusFault | None:
    """The BusFault of a recorded event (None: not a readable bus-exception note)."""
    detail = event.get("detail")
    if event.get("kind") != "note" or not isinstance(detail, Mapping):
        return None
    where = detail.get("bus_exception")
    errno = detail.get("errno")
    fid = detail.get("arbitration_id")
    if where not in ("recv", "send") or not (errno is None or type(errno) is int):
        return None
    if where == "send" and type(fid) is not int:
        return None
    try:
        tick = int(event["tick"])
    except (KeyError, TypeError, ValueError):
        return None
    return BusFault(tick, str(where), str(detail.get("type", "CanOperationError")),
                    str(detail.get("error", "")), errno,
                    fid if where == "send" else None)


class SendAttempts:
    """Numbers each failed send among the send attempts of its frame ID in its tick.

    Fed piece by piece with the piece's ``/can/tx`` frames and failed sends, each with
    its MCAP sequence number (file order across the two topics).  A tick's items may
    straddle two pieces: the attempts counted for the last tick seen are carried over.
    Assumes ticks never decrease in file order (the loop's)."""

    def __init__(self) -> None:
        self._carry: dict[tuple[int, int], int] = {}
        self._last_tick = -1

    def number(self, tx: Sequence[tuple[int, int, bytes, int]], tx_seq: Sequence[int],
               failed: Sequence[tuple[int, BusFault]]) -> list[BusFault]:
        """``failed``: (sequence, send fault) in file order -> the faults with their
        ``attempt`` set.  ``tx``: (tick, id, data, flags) with sequences ``tx_seq``."""
        counts = self._carry
        out: list[BusFault] = [f for _, f in failed]
        want = {(f.tick, int(f.arbitration_id or 0)) for _, f in failed}
        if failed:
            items: list[tuple[int, tuple[int, int], int]] = []   # (seq, key, fault no.)
            for frame, seq in zip(tx, tx_seq, strict=True):
                key = (frame[0], frame[1])
                if key in want:
                    items.append((seq, key, -1))
            for j, (seq, f) in enumerate(failed):
                items.append((seq, (f.tick, int(f.arbitration_id or 0)), j))
            items.sort(key=lambda it: it[0])
            for _, key, j in items:
                n = counts.get(key, 0)
                counts[key] = n + 1
                if j >= 0:
                    out[j] = replace(out[j], attempt=n)
        last = max(self._last_tick, tx[-1][0] if tx else -1,
                   max((f.tick for _, f in failed), default=-1))
        for frame in reversed(tx):     # the last tick may go on in the next piece
            if frame[0] != last:
                break
            key = (frame[0], frame[1])
            if key not in want:
                counts[key] = counts.get(key, 0) + 1
        self._carry = {k: v for k, v in counts.items() if k[0] == last}
        self._last_tick = last
        return out
