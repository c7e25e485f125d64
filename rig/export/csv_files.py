"""A run as CSV files (pyarrow's CSV writer), one per table, in a directory: the files
and columns of the Parquet export (:mod:`rig.export.parquet`) as ``.csv``:
``rig_signals.csv``, ``controller_internals.csv``, ``rig_timing.csv`` (``t_s``,
``t_ns``, ``tick``, then one column per field) and ``can.csv`` (``t_s``, ``t_ns``,
``tick``, ``id``, ``dlc``, ``data`` as hex digits, ``direction`` ``rx`` / ``tx``,
``error_frame``, ``extended_id`` ``true`` / ``false``).

One header line of column names; CSV has no place for units, they follow from the names'
suffixes (:func:`rig.export.tables.unit_of`: ``_m`` m, ``_n`` N ...).  A value not
recorded (NaN in the other formats) is an empty field; floats are written in the
shortest form that reads back to the same double."""

from __future__ import annotations

from pathlib import Path
from typing import Final

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from rig.export.parquet import can_table, table_file, topic_table
from rig.export.tables import RunTables

__all__ = ["CAN_CSV", "CsvStream", "csv_file"]

CAN_CSV: Final = "can.csv"
_OPTIONS: Final = pacsv.WriteOptions(quoting_style="none")


def csv_file(topic: str) -> str:
    """The file of a tick topic: ``/rig/signals`` -> ``rig_signals.csv``."""
    return table_file(topic).removesuffix(".parquet") + ".csv"


def _for_csv(table: pa.Table) -> pa.Table:
    """NaN as a missing value, bytes as hex digits, dictionary text as text."""
    columns = []
    for col in table.columns:
        arr = col.combine_chunks()
        if pa.types.is_floating(arr.type):
            values = arr.to_numpy(zero_copy_only=False)
            arr = pa.array(values, mask=np.isnan(values))
        elif pa.types.is_binary(arr.type):
            arr = pa.array([None if b is None else b.hex() for b in arr.to_pylist()],
                           type=pa.string())
        elif pa.types.is_dictionary(arr.type):
            arr = arr.cast(pa.string())
        columns.append(arr)
    return pa.Table.from_arrays(columns, names=table.column_names)


class CsvStream:
    """The CSV files of a run built batch by batch (:meth:`add`) into the (new, empty)
    directory ``out_dir``."""

    def __init__(self, out_dir: str | Path) -> None:
        self.out = Path(out_dir)
        self.writers: dict[str, pacsv.CSVWriter] = {}

    def add(self, tables: RunTables) -> None:
        for table in tables.topics:
            self._write(csv_file(table.topic), topic_table(table, tables))
        if len(tables.can) or CAN_CSV not in self.writers:
            self._write(CAN_CSV, can_table(tables.can, tables))

    def _write(self, name: str, table: pa.Table) -> None:
        table = _for_csv(table)
        writer = self.writers.get(name)
        if writer is None:
            writer = self.writers[name] = pacsv.CSVWriter(self.out / name, table.schema,
                                                          write_options=_OPTIONS)
        writer.write_table(table)

    def close(self) -> list[Path]:
        """Finish the files; returns them."""
        for writer in self.writers.values():
            writer.close()
        return [self.out / name for name in self.writers]
