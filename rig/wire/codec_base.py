"""The hand-written part of the CAN codec that no DBC number enters: the decode status,
the signal description, the base classes of the frame objects and of the codecs.

The per-frame code (frame classes with their fields, ``encode`` / ``decode`` with the
DBC's bit positions, scales, ranges and ``VAL_`` tables written in as literals) is
generated from ``rig/wire/rig.dbc`` into :mod:`rig.wire.dbc_codec` by
``python -m rig.wire.generate``; :mod:`rig.wire.protocol` is the public face of both.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum
from typing import Any, ClassVar, NamedTuple

__all__ = ["Codec", "DecodeStatus", "Frame", "SignalSpec"]


class DecodeStatus(IntEnum):
    OK = 0
    BAD_LENGTH = 1  #: payload is not exactly 8 bytes
    UNKNOWN_ID = 2  #: not a frame of this protocol (a decoder by frame ID; the codecs never)
    BAD_CRC = 3  #: E2E CRC mismatch: corrupted frame or wrong data ID
    OUT_OF_RANGE = 4  #: intact, fields filled, some value outside DBC range (range_mask)


class SignalSpec(NamedTuple):
    """One DBC signal as this codec sees it (checked against cantools by the tests)."""

    attr: str  #: attribute of the frame object
    dbc_name: str
    start_bit: int
    length: int
    signed: bool
    scale: float
    minimum: float
    maximum: float
    choices: tuple[int, ...] | None = None  #: defined VAL_ values, if any


class Frame:
    """Base of the mutable, preallocated frame objects (``__slots__`` only)."""

    __slots__ = ("counter", "range_mask")
    FIELDS: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **values: Any) -> None:
        self.counter = 0
        self.range_mask = 0
        for name in self.FIELDS:
            setattr(self, name, 0)
        for name, value in values.items():
            if name not in self.FIELDS and name != "counter":
                raise TypeError(f"{type(self).__name__} has no field {name!r}")
            setattr(self, name, value)

    def __repr__(self) -> str:
        body = ", ".join(f"{n}={getattr(self, n)!r}" for n in ("counter", *self.FIELDS))
        return f"{type(self).__name__}({body})"

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        names = ("counter", *self.FIELDS)
        return all(getattr(self, n) == getattr(other, n) for n in names)

    __hash__ = None  # type: ignore[assignment]


class Codec:
    """Common part of the frame codecs; each generated subclass adds
    ``encode(buf, counter, *fields) -> clamp mask`` and ``decode(data, out) -> status``."""

    FRAME_ID: ClassVar[int]
    NAME: ClassVar[str]
    FRAME_TYPE: ClassVar[type[Frame]]
    COUNTER_SIGNAL: ClassVar[str]
    SIGNALS: ClassVar[tuple[SignalSpec, ...]]

    def __init__(self) -> None:
        self.frame_id = self.FRAME_ID
        self.name = self.NAME

    def new(self) -> Any:
        """A fresh (zeroed) frame object for ``decode``."""
        return self.FRAME_TYPE()

    def encode_frame(self, buf: bytearray | memoryview, frame: Frame) -> int:
        """Encode a frame object (its ``counter`` and fields); returns the clamp mask."""
        args = [getattr(frame, n) for n in self.FRAME_TYPE.FIELDS]
        return int(self.encode(buf, frame.counter, *args))  # type: ignore[attr-defined]

    def encode_signals(self, buf: bytearray | memoryview, signals: Mapping[str, float]) -> int:
        """Encode from a ``{DBC signal name: physical value}`` mapping (CRC signal ignored,
        missing signals 0).  Not for the hot path."""
        frame = self.FRAME_TYPE()
        frame.counter = int(signals.get(self.COUNTER_SIGNAL, 0))
        for spec in self.SIGNALS:
            setattr(frame, spec.attr, signals.get(spec.dbc_name, 0))
        return self.encode_frame(buf, frame)

    def to_signals(self, frame: Frame) -> dict[str, float]:
        """``{DBC signal name: value}`` of a decoded frame (counter included, CRC not)."""
        out: dict[str, float] = {self.COUNTER_SIGNAL: frame.counter}
        for spec in self.SIGNALS:
            out[spec.dbc_name] = getattr(frame, spec.attr)
        return out
