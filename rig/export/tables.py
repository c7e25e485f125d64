"""A recorded run as columns: one :class:`TopicTable` per tick topic (``/rig/signals``,
``/controller/internals``, ``/rig/timing``; the fields split by the recording schema's
:data:`~rig.recording.schema.SIGNAL_KEYS` / :data:`~rig.recording.schema.TIMING_KEYS`)
and the CAN bus log (:class:`CanLog`, ``/can/rx`` and ``/can/tx`` in recording order).

Every numeric field becomes a column: integers (and booleans) ``int64`` when every
record has one, else ``float64`` with NaN for a value not recorded or non-finite
(``None`` in :func:`~rig.recording.read_run`); a list field (``x_post``, ``q`` ...) one
column per element, ``name[i]``.  Text fields (``fault``) are left out and named in
:attr:`RunTables.skipped`.  Times: ``t_ns`` is the loop clock as recorded; ``t_s`` is
seconds since :attr:`RunTables.t0_ns` (the run's first item), the time base of every
table; :attr:`RunTables.start_wall_ns` is that instant on the wall clock."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from rig.recording.run_data import RunData
from rig.recording.schema import (
    SIGNAL_KEYS,
    TIMING_KEYS,
    TOPIC_INTERNALS,
    TOPIC_SIGNALS,
    TOPIC_TIMING,
)

__all__ = ["CAN_DATA_BYTES", "CanLog", "RunTables", "TableSchema", "TopicTable", "clock_offset_ns",
           "run_tables", "unit_of"]

#: classic CAN: at most 8 data bytes (the loop runs classic CAN, docs/recording.md)
CAN_DATA_BYTES: Final = 8
#: SI unit of a field, by the suffix of its name (the recording's naming convention)
_UNITS: Final = (("_mps2", "m/s^2"), ("_mps", "m/s"), ("_m", "m"), ("_n", "N"),
                 ("_s", "s"), ("_ns", "ns"), ("_hz", "Hz"), ("_ticks", "tick"))
_NOT_FIELDS: Final = frozenset({"tick", "t_ns"})


def unit_of(name: str) -> str:
    """The SI unit of the field ``name`` (``""`` when it has none: counts, codes, flags,
    normalised values)."""
    base = name.split("[", 1)[0]
    for suffix, unit in _UNITS:
        if base.endswith(suffix):
            return unit
    return ""


@dataclass
class TopicTable:
    topic: str
    t_ns: NDArray[np.int64]
    tick: NDArray[np.int64]
    columns: dict[str, NDArray[Any]] = field(default_factory=dict)

    @property
    def units(self) -> dict[str, str]:
        return {name: unit_of(name) for name in self.columns}


@dataclass
class CanLog:
    """The frames of ``/can/rx`` and ``/can/tx`` in recording order."""

    t_ns: NDArray[np.int64]
    tick: NDArray[np.int64]
    arbitration_id: NDArray[np.uint32]
    dlc: NDArray[np.uint8]
    data: NDArray[np.uint8]           # (n, CAN_DATA_BYTES), zero-padded past dlc
    is_rx: NDArray[np.bool_]
    is_error_frame: NDArray[np.bool_]
    is_extended_id: NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.t_ns.size)


@dataclass
class RunTables:
    topics: list[TopicTable]
    can: CanLog
    t0_ns: int
    start_wall_ns: int
    skipped: list[str]

    def seconds(self, t_ns: NDArray[np.int64]) -> NDArray[np.float64]:
        """Seconds since :attr:`t0_ns` (the common time base)."""
        return (t_ns - self.t0_ns).astype(np.float64) * 1e-9


def _topic_of(key: str) -> str:
    if key in SIGNAL_KEYS:
        return TOPIC_SIGNALS
    if key in TIMING_KEYS:
        return TOPIC_TIMING
    return TOPIC_INTERNALS


#: the types of JSON values that make an ``int64`` column / a ``float64`` one (checked
#: as a set first: one C loop over the values; other types one by one)
_INT_TYPES: Final = frozenset({int, bool})
_NUMBER_TYPES: Final = frozenset({int, bool, float, type(None)})
_LIST_TYPES: Final = frozenset({list})


def _column(values: Sequence[Any]) -> NDArray[Any] | None:
    """One numeric column, or None when the values are not numbers."""
    types = set(map(type, values))
    if types <= _INT_TYPES:
        return np.array(values, dtype=np.int64)
    if types <= _NUMBER_TYPES or all(v is None or isinstance(v, int | float)
                                     for v in values):
        return np.array(values, dtype=np.float64)        # None -> NaN
    return None


def _list_columns(name: str, values: list[Any]) -> dict[str, NDArray[Any]] | None:
    if set(map(type, values)) <= _LIST_TYPES:           # lists only: by element
        if len(set(map(len, values))) != 1:
            return None
        elements: Iterable[Sequence[Any]] = zip(*values, strict=True)
    else:
        lengths = {len(v) for v in values if isinstance(v, list)}
        if len(lengths) != 1 or not all(v is None or isinstance(v, list) for v in values):
            return None
        elements = ([None if v is None else v[i] for v in values]
                    for i in range(lengths.pop()))
    out: dict[str, NDArray[Any]] = {}
    for i, element in enumerate(elements):
        col = _column(element)
        if col is None:
            return None
        out[f"{name}[{i}]"] = col
    return out


def _can_log(run: RunData) -> CanLog:
    frames = run.frames
    n = len(frames)
    data = np.zeros((n, CAN_DATA_BYTES), dtype=np.uint8)
    for i, f in enumerate(frames):
        data[i, :len(f.data)] = np.frombuffer(f.data[:CAN_DATA_BYTES], dtype=np.uint8)
    return CanLog(
        t_ns=np.array([f.t_ns for f in frames], dtype=np.int64),
        tick=np.array([f.tick for f in frames], dtype=np.int64),
        arbitration_id=np.array([f.arbitration_id for f in frames], dtype=np.uint32),
        dlc=np.array([len(f.data) for f in frames], dtype=np.uint8),
        data=data,
        is_rx=np.array([f.is_rx for f in frames], dtype=np.bool_),
        is_error_frame=np.array([f.is_error_frame for f in frames], dtype=np.bool_),
        is_extended_id=np.array([f.is_extended_id for f in frames], dtype=np.bool_))


class TableSchema:
    """The columns of a run, decided over all of its tick records (observed batch by
    batch, :meth:`observe`): a key's kind (scalar, list of a width, or left out) and
    each column's dtype are what :func:`_column` / :func:`_list_columns` give for the
    whole run at once, whatever the batches."""

    def __init__(self) -> None:
        self.widths: dict[str, int | None] = {}   # key -> None scalar, n list, -1 out
        self.floats: set[str] = set()             # columns with a None or a float
        self.seen: set[str] = set()               # keys with a value (not None)
        self.batches = 0
        self.t0_ns: int | None = None
        self.has_can = {False: False, True: False}  # is_error_frame -> any
        #: the columns of the batch observed last, as observed (:meth:`tables` reuses
        #: them for that batch instead of collecting its values again)
        self._observed: RunData | None = None
        self._observed_cols: dict[str, NDArray[Any]] = {}

    def observe(self, run: RunData) -> None:
        self._observed, self._observed_cols = run, {}
        records = run.records
        keys: dict[str, None] = {}
        for r in records:
            keys.update(dict.fromkeys(r.data))
        for key in self.widths.keys() - keys:       # absent in this batch: None
            self._float_all(key)
        datas = [r.data for r in records]
        for key in keys:
            if key in _NOT_FIELDS:
                continue
            if key not in self.widths:
                self.widths[key] = None
                if self.batches:                    # absent in the earlier batches
                    self._float_all(key)
            self._observe(key, [d.get(key) for d in datas])
        firsts = [r.t_ns for r in records[:1]] + [f.t_ns for f in run.frames[:1]]
        if firsts and self.t0_ns is None:
            self.t0_ns = min(firsts)
        for f in run.frames:
            self.has_can[f.is_error_frame] = True
        self.batches += 1

    def _float_all(self, key: str) -> None:
        self.floats.add(key)
        self.floats.update(f"{key}[{i}]" for i in range(max(self.widths[key] or 0, 0)))

    def _observe(self, key: str, values: list[Any]) -> None:
        width = self.widths[key]
        if width == -1 or all(v is None for v in values):
            if width != -1:
                self._float_all(key)
            return
        col = _column(values)
        if col is not None:
            if key in self.seen and width is not None:     # a list before
                self.widths[key] = -1
                return
            self.seen.add(key)
            if col.dtype != np.int64:
                self.floats.add(key)
            self._observed_cols[key] = col
            return
        cols = _list_columns(key, values)
        n = len(cols) if cols is not None else -1
        if cols is None or (key in self.seen and width != n):
            self.widths[key] = -1
            return
        self.seen.add(key)
        self._observed_cols.update(cols)
        self.widths[key] = n
        if key in self.floats:                     # a None before the width was known
            self.floats.update(cols)
        self.floats.update(name for name, c in cols.items() if c.dtype != np.int64)

    def layout(self) -> tuple[Any, ...]:
        """Everything :meth:`tables` lays a batch out by: the time base, the columns in
        order with their dtype (float or not), the keys left out.  Two schemas with equal
        layouts give every batch the same tables."""
        columns = tuple((name, name in self.floats) for key in self.widths
                        for name in self.columns(key))
        return self.t0_ns, columns, tuple(self.skipped)

    @property
    def skipped(self) -> list[str]:
        return [k for k, w in self.widths.items() if w == -1]

    def columns(self, key: str) -> list[str]:
        """The columns of ``key`` (none when it is left out)."""
        width = self.widths[key]
        if width == -1:
            return []
        return [key] if width is None else [f"{key}[{i}]" for i in range(width)]

    def tables(self, run: RunData, start_wall_offset_ns: int = 0) -> RunTables:
        """The columns of the batch ``run`` with the run's kinds and dtypes."""
        records = run.records
        t_ns = np.array([r.t_ns for r in records], dtype=np.int64)
        tick = np.array([r.tick for r in records], dtype=np.int64)
        tables = {t: TopicTable(t, t_ns, tick) for t in (TOPIC_SIGNALS, TOPIC_INTERNALS,
                                                         TOPIC_TIMING)}
        observed = self._observed_cols if run is self._observed else {}
        self._observed, self._observed_cols = None, {}     # used once: free the batch
        for key, width in self.widths.items():
            if width == -1:
                continue
            cols = tables[_topic_of(key)].columns
            names = self.columns(key)
            if all(name in observed for name in names):
                for name in names:
                    cols[name] = self._as_decided(name, observed[name])
                continue
            values = [r.data.get(key) for r in records]
            if width is None:
                cols[key] = self._array(key, values)
                continue
            for i, name in enumerate(self.columns(key)):
                cols[name] = self._array(name, [None if v is None else v[i]
                                                for v in values])
        t0 = self.t0_ns or 0
        return RunTables(topics=[t for t in tables.values() if t.columns],
                         can=_can_log(run), t0_ns=t0,
                         start_wall_ns=t0 + start_wall_offset_ns, skipped=self.skipped)

    def _array(self, name: str, values: list[Any]) -> NDArray[Any]:
        return np.array(values, dtype=np.float64 if name in self.floats else np.int64)

    def _as_decided(self, name: str, col: NDArray[Any]) -> NDArray[Any]:
        """A column as :func:`_column` made it for one batch, in the run's dtype (an
        ``int64`` column of a float column: the same values :meth:`_array` gives)."""
        if name in self.floats and col.dtype != np.float64:
            return col.astype(np.float64)
        return col


def clock_offset_ns(run: RunData) -> int:
    """Loop clock -> wall clock (the recording's ``rig`` metadata)."""
    return int(run.metadata.get("rig", {}).get("clock_offset_ns", "0") or 0)


def run_tables(run: RunData) -> RunTables:
    """The columns of ``run`` (see the module docstring)."""
    schema = TableSchema()
    schema.observe(run)
    return schema.tables(run, clock_offset_ns(run))
