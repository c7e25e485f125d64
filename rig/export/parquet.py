"""A run as Parquet files (pyarrow), one per table, in a directory:
``rig_signals.parquet``, ``controller_internals.parquet``, ``rig_timing.parquet`` (the
tick topics: ``t_s``, ``t_ns``, ``tick``, then one column per field, its SI unit in the
field metadata ``unit``) and ``can.parquet`` (``t_s``, ``t_ns``, ``tick``, ``id``,
``dlc``, ``data`` (bytes), ``direction`` (``rx`` / ``tx``), ``error_frame``,
``extended_id``).  ``t_s``: seconds since the run's first item; the file metadata
``start_wall_ns`` is that instant on the wall clock."""

from __future__ import annotations

from pathlib import Path
from typing import Final

import pyarrow as pa
import pyarrow.parquet as pq

from rig.export.tables import CanLog, RunTables, TopicTable

__all__ = ["CAN_FILE", "ParquetStream", "can_table", "table_file", "topic_table", "write_parquet"]

CAN_FILE: Final = "can.parquet"


def table_file(topic: str) -> str:
    """The file of a tick topic: ``/rig/signals`` -> ``rig_signals.parquet``."""
    return topic.strip("/").replace("/", "_") + ".parquet"


def _time_fields(tables: RunTables) -> dict[bytes, bytes]:
    return {b"start_wall_ns": str(tables.start_wall_ns).encode(),
            b"t0_ns": str(tables.t0_ns).encode()}


def can_table(can: CanLog, tables: RunTables) -> pa.Table:
    """The frames of a batch as an Arrow table (the columns of ``can.parquet``)."""
    data = [bytes(row[:n]) for row, n in zip(can.data, can.dlc, strict=True)]
    return pa.table({
        "t_s": pa.array(tables.seconds(can.t_ns)),
        "t_ns": pa.array(can.t_ns),
        "tick": pa.array(can.tick),
        "id": pa.array(can.arbitration_id),
        "dlc": pa.array(can.dlc),
        "data": pa.array(data, type=pa.binary()),
        "direction": pa.array(["rx" if rx else "tx" for rx in can.is_rx.tolist()],
                              type=pa.dictionary(pa.int8(), pa.string())),
        "error_frame": pa.array(can.is_error_frame),
        "extended_id": pa.array(can.is_extended_id),
    }).replace_schema_metadata(_time_fields(tables))


def topic_table(table: TopicTable, tables: RunTables) -> pa.Table:
    """A tick topic's batch as an Arrow table (``t_s``, ``t_ns``, ``tick``, the fields
    with their units in the field metadata)."""
    fields = [pa.field("t_s", pa.float64(), metadata={"unit": "s"}),
              pa.field("t_ns", pa.int64(), metadata={"unit": "ns"}),
              pa.field("tick", pa.int64())]
    arrays = [pa.array(tables.seconds(table.t_ns)), pa.array(table.t_ns),
              pa.array(table.tick)]
    for (name, col), unit in zip(table.columns.items(), table.units.values(),
                                 strict=True):
        arr = pa.array(col)
        fields.append(pa.field(name, arr.type, metadata={"unit": unit} if unit else None))
        arrays.append(arr)
    schema = pa.schema(fields, metadata={**_time_fields(tables),
                                         b"topic": table.topic.encode()})
    return pa.Table.from_arrays(arrays, schema=schema)


class ParquetStream:
    """The Parquet files of a run built batch by batch (:meth:`add`), one row group
    per batch, into the (new, empty) directory ``out_dir``."""

    def __init__(self, out_dir: str | Path) -> None:
        self.out = Path(out_dir)
        self.writers: dict[str, pq.ParquetWriter] = {}

    def add(self, tables: RunTables) -> None:
        for table in tables.topics:
            self._write(table_file(table.topic), topic_table(table, tables))
        if len(tables.can) or CAN_FILE not in self.writers:
            self._write(CAN_FILE, can_table(tables.can, tables))

    def _write(self, name: str, table: pa.Table) -> None:
        writer = self.writers.get(name)
        if writer is None:
            writer = self.writers[name] = pq.ParquetWriter(self.out / name, table.schema)
        writer.write_table(table)

    def close(self) -> list[Path]:
        """Finish the files; returns them."""
        for writer in self.writers.values():
            writer.close()
        return [self.out / name for name in self.writers]


def write_parquet(tables: RunTables, out_dir: str | Path) -> list[Path]:
    """Write the tables into the (new, empty) directory ``out_dir``; returns the files."""
    out = ParquetStream(out_dir)
    out.add(tables)
    return out.close()
