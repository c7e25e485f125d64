"""Declarative layout of the runtime's packed buffers.

Each buffer (``fv``, ``iv`` and the columns of ``mat``, ``vec``, ``st``) is declared as an
ordered list of slots with their sizes; the offsets follow from the order, so two slots can
never overlap and nothing is numbered by hand.  The offsets are plain module-level ``int``
constants of :mod:`controller.runtime.kernels` (numba freezes them into the compiled step).
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar, overload

__all__ = ["BufferLayout", "Slot", "SlotValue"]

T = TypeVar("T")


@dataclass(frozen=True)
class Slot:
    """``size`` consecutive entries of a buffer from ``offset``."""

    offset: int
    size: int

    @property
    def end(self) -> int:
        """One past the last entry."""
        return self.offset + self.size


@dataclass
class BufferLayout:
    """Slots of one buffer, in declaration order (offsets assigned consecutively)."""

    buffer: str
    slots: list[Slot] = field(default_factory=list)

    @property
    def size(self) -> int:
        """Entries the declared slots take (the head of whatever follows them)."""
        return self.slots[-1].end if self.slots else 0

    def slot(self, size: int = 1) -> int:
        """Declare the next slot of ``size`` entries; returns its offset."""
        if size < 1:
            raise ValueError(f"{self.buffer}: a slot needs at least one entry, got {size}")
        s = Slot(self.size, size)
        self.slots.append(s)
        return s.offset


class SlotValue(Generic[T]):
    """A read-only attribute that reads one entry of a buffer its owner holds: a
    declarative property for the read-outs of packed state (``kind`` converts the NumPy
    scalar, e.g. ``float`` or ``bool``)."""

    def __init__(self, buffer_attr: str, offset: int, kind: Callable[[Any], T],
                 doc: str | None = None) -> None:
        self._get_buffer = operator.attrgetter(buffer_attr)
        self.offset = offset
        self.kind = kind
        self.__doc__ = doc

    @overload
    def __get__(self, obj: None, objtype: type | None = None) -> SlotValue[T]: ...

    @overload
    def __get__(self, obj: object, objtype: type | None = None) -> T: ...

    def __get__(self, obj: object | None, objtype: type | None = None) -> SlotValue[T] | T:
        if obj is None:
            return self
        return self.kind(self._get_buffer(obj)[self.offset])
