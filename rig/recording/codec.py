"""Wire format between the loop process and the recording writer process.

The loop never encodes JSON or touches MCAP: :class:`rig.recording.recorder.RunRecorder` packs
each item into a few bytes and hands a whole tick's batch to a pipe; the writer process
(:mod:`rig.recording.writer`) decodes the items with this module and writes the MCAP file.
Both ends come from the same installation, so the format is internal; it is versioned
(:data:`STREAM_MAGIC`) only to fail clearly if they ever differ.

Stream: ``STREAM_MAGIC``, u32 header length, header JSON, u32 design length, design
bytes, then items.  Every item (little endian) starts with ``u32 size`` (whole item,
this field included) and ``u8 kind``:

=================  =========================================================
``ITEM_FRAME``     ``q t_ns, q tick, I arbitration_id, B flags, B dlc``, data
``ITEM_TICK``      ``q t_ns``, the scalars of the :class:`TickLayout` in one
                   struct, then each array's raw bytes (C order)
``ITEM_PICKLED``   ``q t_ns``, pickle of a tick-record dict (generic callers)
``ITEM_EVENT``     ``q t_ns, q tick``, pickle of ``(kind, detail)``
``ITEM_LAYOUT``    JSON of the :class:`TickLayout` of the ITEM_TICKs that follow
``ITEM_END``       nothing: the producer closed the recording on purpose
=================  =========================================================

A :class:`TickLayout` names the fields of the loop's tick record (scalars with a *kind*
that says how the writer turns the packed value into the JSON value, and fixed-shape
arrays); it travels in the stream (ITEM_LAYOUT) so the writer can unpack without
knowing the loop.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

__all__ = [
    "FRAME_ERROR",
    "FRAME_EXTENDED",
    "FRAME_HEAD",
    "FRAME_RX",
    "ITEM_END",
    "ITEM_EVENT",
    "ITEM_FRAME",
    "ITEM_HEAD",
    "ITEM_LAYOUT",
    "ITEM_PICKLED",
    "ITEM_TICK",
    "STREAM_MAGIC",
    "TickLayout",
    "TickPacker",
    "decode_item",
    "encode_end",
    "encode_event",
    "encode_header",
    "encode_layout",
    "encode_pickled_tick",
    "split_items",
]

STREAM_MAGIC: Final = b"RIGREC02"
ITEM_FRAME: Final = 0
ITEM_TICK: Final = 1
ITEM_PICKLED: Final = 2
ITEM_EVENT: Final = 3
ITEM_LAYOUT: Final = 4
ITEM_END: Final = 255

#: frame flag bits
FRAME_RX: Final = 1
FRAME_ERROR: Final = 2
FRAME_EXTENDED: Final = 4

ITEM_HEAD: Final = struct.Struct("<IB")               # size, kind
FRAME_HEAD: Final = struct.Struct("<IBqqIBB")         # size, kind, t_ns, tick, id, flags, dlc
_T_NS: Final = struct.Struct("<IBq")                  # size, kind, t_ns
_EVENT_HEAD: Final = struct.Struct("<IBqq")           # size, kind, t_ns, tick
_U32: Final = struct.Struct("<I")

#: scalar kinds: struct code and how the writer turns the packed value into JSON
SCALAR_KINDS: Final[dict[str, str]] = {
    "int": "q",        # int
    "float": "d",      # float (non-finite: see schema.encode_message)
    "bool": "?",       # bool
    "ns_as_s": "q",    # int nanoseconds -> float seconds (ns * 1e-9); negative -> NaN
    "enum": "B",       # index into the field's names; names[0] may be None
}
_ARRAY_DTYPES: Final = frozenset({"<f8", "|b1", "<i8", "<i4", "|u1"})


@dataclass(frozen=True)
class TickLayout:
    """The fields of a packed tick record, in record (key) order.

    ``fields``: ``(key, kind, names)`` for a scalar (``names`` only for kind ``enum``,
    else ``None``) or ``(key, dtype_str, shape)`` for an array (``dtype_str`` one of
    ``<f8 |b1 <i8 <i4 |u1``).  ``tick`` must be the first field, kind ``int``."""

    fields: tuple[tuple[str, str, Any], ...]

    def __post_init__(self) -> None:
        if not self.fields or self.fields[0][:2] != ("tick", "int"):
            raise ValueError("a tick layout starts with ('tick', 'int', None)")
        keys = [f[0] for f in self.fields]
        if len(set(keys)) != len(keys):
            raise ValueError(f"duplicate keys in tick layout: {keys}")
        for key, kind, extra in self.fields:
            if kind in SCALAR_KINDS:
                if (kind == "enum") != (extra is not None):
                    raise ValueError(f"{key}: names are given for (and only for) kind enum")
            elif kind in _ARRAY_DTYPES:
                if not all(isinstance(n, int) and n >= 0 for n in extra):
                    raise ValueError(f"{key}: shape {extra!r} must be non-negative ints")
            else:
                raise ValueError(f"{key}: kind {kind!r} is neither a scalar kind "
                                 f"{sorted(SCALAR_KINDS)} nor an array dtype "
                                 f"{sorted(_ARRAY_DTYPES)}")

    @property
    def scalar_fields(self) -> tuple[tuple[str, str, Any], ...]:
        return tuple(f for f in self.fields if f[1] in SCALAR_KINDS)

    @property
    def array_fields(self) -> tuple[tuple[str, str, Any], ...]:
        return tuple(f for f in self.fields if f[1] not in SCALAR_KINDS)

    def scalar_struct(self) -> struct.Struct:
        """Item head (size, kind, t_ns) followed by every scalar, packed."""
        return struct.Struct("<IBq" + "".join(SCALAR_KINDS[f[1]]
                                              for f in self.scalar_fields))

    def item_size(self) -> int:
        n = self.scalar_struct().size
        for _, dt, shape in self.array_fields:
            n += np.dtype(dt).itemsize * int(np.prod(shape, dtype=np.int64))
        return n

    def to_json(self) -> list[list[Any]]:
        return [[k, kind, list(extra) if isinstance(extra, tuple) else extra]
                for k, kind, extra in self.fields]

    @classmethod
    def from_json(cls, spec: Sequence[Sequence[Any]]) -> TickLayout:
        fields = []
        for key, kind, extra in spec:
            if kind in SCALAR_KINDS:
                fields.append((str(key), str(kind),
                               None if extra is None else tuple(extra)))
            else:
                fields.append((str(key), str(kind), tuple(int(n) for n in extra)))
        return cls(tuple(fields))


class TickPacker:
    """Packs one tick record per call into a preallocated buffer (no allocation but the
    struct call's own): scalars in one ``struct.pack_into``, arrays copied through
    numpy views made once."""

    def __init__(self, layout: TickLayout) -> None:
        self.layout = layout
        self._head = layout.scalar_struct()
        self.size = layout.item_size()
        self.buffer = bytearray(self.size)
        self._views: list[np.ndarray] = []
        off = self._head.size
        for _, dt, shape in layout.array_fields:
            dtype = np.dtype(dt)
            count = int(np.prod(shape, dtype=np.int64))
            self._views.append(np.frombuffer(self.buffer, dtype, count, off).reshape(shape))
            off += dtype.itemsize * count
        self.n_scalars = len(layout.scalar_fields)
        self.n_arrays = len(self._views)

    def pack(self, t_ns: int, scalars: Sequence[Any], arrays: Sequence[np.ndarray]) -> None:
        """Fill :attr:`buffer` with one ITEM_TICK (``scalars`` / ``arrays`` in layout
        order; enum fields as their index).  Raises on a wrong count, shape or type."""
        if len(arrays) != self.n_arrays:
            raise ValueError(f"tick record: {len(arrays)} arrays, layout has {self.n_arrays}")
        self._head.pack_into(self.buffer, 0, self.size, ITEM_TICK, t_ns, *scalars)
        for view, arr in zip(self._views, arrays, strict=True):
            view[...] = arr


def encode_header(header: Mapping[str, Any], design: bytes | None) -> bytes:
    blob = json.dumps(header, sort_keys=True).encode()
    d = design or b""
    return STREAM_MAGIC + _U32.pack(len(blob)) + blob + _U32.pack(len(d)) + d


def _with_head(kind: int, head: struct.Struct, *values: Any, payload: bytes) -> bytes:
    size = head.size + len(payload)
    return head.pack(size, kind, *values) + payload


def encode_pickled_tick(t_ns: int, record: Mapping[str, Any]) -> bytes:
    return _with_head(ITEM_PICKLED, _T_NS, t_ns,
                      payload=pickle.dumps(dict(record), protocol=pickle.HIGHEST_PROTOCOL))


def encode_event(t_ns: int, tick: int, kind: str, detail: Any) -> bytes:
    try:
        payload = pickle.dumps((kind, detail), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:          # unpicklable detail: keep its text
        payload = pickle.dumps((kind, repr(detail)), protocol=pickle.HIGHEST_PROTOCOL)
    return _with_head(ITEM_EVENT, _EVENT_HEAD, t_ns, tick, payload=payload)


def encode_layout(layout: TickLayout) -> bytes:
    return _with_head(ITEM_LAYOUT, ITEM_HEAD, payload=json.dumps(layout.to_json()).encode())


def encode_end() -> bytes:
    return ITEM_HEAD.pack(ITEM_HEAD.size, ITEM_END)


def read_exact(fd: int, n: int, what: str) -> bytes:
    """``n`` bytes from the pipe ``fd`` (blocking); EOFError naming ``what`` if it ends first."""
    out = bytearray()
    while len(out) < n:
        chunk = os.read(fd, n - len(out))
        if not chunk:
            raise EOFError(f"{what} ended after {len(out)} of {n} header bytes")
        out += chunk
    return bytes(out)


def read_stream_header(fd: int, magic: bytes, what: str) -> dict[str, Any]:
    """The head of a stream a child process reads on its stdin (the recorder's writer,
    the telemetry process): ``magic``, a u32 length, that many bytes of JSON.
    ValueError when the magic is not ``magic``, EOFError when the stream ends early."""
    got = read_exact(fd, len(magic), what)
    if got != magic:
        raise ValueError(f"not a {what} (magic {got!r})")
    (hlen,) = _U32.unpack(read_exact(fd, 4, what))
    header = json.loads(read_exact(fd, hlen, what))
    if not isinstance(header, dict):
        raise ValueError(f"{what}: the header is not a JSON object")
    return header


def split_items(buf: bytes | bytearray | memoryview, start: int = 0
                ) -> tuple[int, int]:
    """(offset just past the last complete item, number of complete items) from ``start``."""
    n = len(buf)
    pos, count = start, 0
    unpack = _U32.unpack_from
    while pos + 5 <= n:
        (size,) = unpack(buf, pos)
        if size < 5:
            raise ValueError(f"corrupt recording stream: item size {size} at byte {pos}")
        if pos + size > n:
            break
        pos += size
        count += 1
    return pos, count


class TickDecoder:
    """Writer side: ITEM_TICK bytes -> the record dict (key order of the layout)."""

    def __init__(self, layout: TickLayout) -> None:
        self.layout = layout
        self._head = layout.scalar_struct()
        self._scalars = layout.scalar_fields
        self._arrays = [(key, np.dtype(dt), shape,
                         int(np.prod(shape, dtype=np.int64)))
                        for key, dt, shape in layout.array_fields]
        self.size = layout.item_size()

    def decode(self, item: bytes | memoryview) -> tuple[int, dict[str, Any]]:
        if len(item) != self.size:
            raise ValueError(f"tick item of {len(item)} bytes, layout says {self.size}")
        values = self._head.unpack_from(item, 0)
        t_ns = values[2]
        out: dict[str, Any] = {}
        for (key, kind, names), v in zip(self._scalars, values[3:], strict=True):
            if kind == "ns_as_s":
                out[key] = v * 1e-9 if v >= 0 else math.nan
            elif kind == "enum":
                out[key] = names[v] if v < len(names) else f"unknown({v})"
            else:
                out[key] = v
        off = self._head.size
        for key, dtype, shape, count in self._arrays:
            out[key] = np.frombuffer(item, dtype, count, off).reshape(shape).tolist()
            off += dtype.itemsize * count
        ordered = {key: out[key] for key, _, _ in self.layout.fields}
        return t_ns, ordered


def decode_item(item: bytes | memoryview, ticks: TickDecoder | None
                ) -> tuple[Any, ...]:
    """One item -> ``("frame", t_ns, tick, id, data, flags)``, ``("tick", t_ns, dict)``,
    ``("event", t_ns, tick, kind, detail)``, ``("layout", TickLayout)`` or ``("end",)``."""
    _size, kind = ITEM_HEAD.unpack_from(item, 0)
    if kind == ITEM_FRAME:
        _, _, t_ns, tick, arb, flags, dlc = FRAME_HEAD.unpack_from(item, 0)
        data = bytes(item[FRAME_HEAD.size:FRAME_HEAD.size + dlc])
        return ("frame", t_ns, tick, arb, data, flags)
    if kind == ITEM_TICK:
        if ticks is None:
            raise ValueError("packed tick record but the stream declared no tick layout")
        t_ns, record = ticks.decode(item)
        return ("tick", t_ns, record)
    if kind == ITEM_PICKLED:
        _, _, t_ns = _T_NS.unpack_from(item, 0)
        return ("tick", t_ns, pickle.loads(item[_T_NS.size:]))
    if kind == ITEM_EVENT:
        _, _, t_ns, tick = _EVENT_HEAD.unpack_from(item, 0)
        ev_kind, detail = pickle.loads(item[_EVENT_HEAD.size:])
        return ("event", t_ns, tick, ev_kind, detail)
    if kind == ITEM_LAYOUT:
        return ("layout", TickLayout.from_json(json.loads(bytes(item[ITEM_HEAD.size:]))))
    if kind == ITEM_END:
        return ("end",)
    raise ValueError(f"corrupt recording stream: item kind {kind}")


def iter_items(buf: bytes | memoryview) -> Iterator[memoryview]:
    """The complete items of ``buf`` (which holds only complete items)."""
    mv = memoryview(buf)
    pos, n = 0, len(mv)
    while pos < n:
        (size,) = _U32.unpack_from(mv, pos)
        yield mv[pos:pos + size]
        pos += size
