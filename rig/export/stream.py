"""``rig export`` in bounded memory: the recording is read twice in batches
(:func:`rig.recording.run_data.stream_run`, ``read_run``'s decoders): the first pass
decides the columns over the whole run (:class:`~rig.export.tables.TableSchema`), the
second lays each batch out and appends it to the MF4 (:class:`~rig.export.mf4.Mf4Stream`)
or the Parquet files (:class:`~rig.export.parquet.ParquetStream`, a row group per
batch).  Peak memory: one batch (``batch_ticks`` records as objects and as columns)
plus the writers' buffers, whatever the length of the run."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rig.export.tables import RunTables, TableSchema, clock_offset_ns
from rig.recording.run_data import STREAM_BATCH_TICKS, RunData, stream_run

__all__ = ["ExportSummary", "export_run"]


@dataclass
class ExportSummary:
    run: RunData                 # metadata, complete, stopped_at (no items)
    records: int = 0
    frames: int = 0
    topics: int = 0
    batches: int = 0
    skipped: list[str] = field(default_factory=list)


def export_run(src: str | Path, fmt: str, out: str | Path, *, comment: str = "",
               batch_ticks: int = STREAM_BATCH_TICKS) -> ExportSummary:
    """Export the recording ``src`` as ``fmt`` (``mf4``: the new file ``out``;
    ``parquet``: into the new, empty directory ``out``)."""
    schema = TableSchema()
    head = stream_run(src, schema.observe, batch_ticks=batch_ticks)
    offset = clock_offset_ns(head)
    summary = ExportSummary(head, skipped=schema.skipped)
    if fmt == "mf4":
        from rig.export.mf4 import Mf4Stream

        mf4 = Mf4Stream((schema.t0_ns or 0) + offset, comment=comment)
        try:
            _stream(src, schema, offset, mf4.add, summary, batch_ticks)
            mf4.save(out)
        finally:
            mf4.close()
    else:
        from rig.export.parquet import ParquetStream

        pq = ParquetStream(out)
        try:
            _stream(src, schema, offset, pq.add, summary, batch_ticks)
        finally:
            pq.close()
    return summary


def _stream(src: str | Path, schema: TableSchema, offset: int,
            add: Callable[[RunTables], None],
            summary: ExportSummary, batch_ticks: int) -> None:
    def on_batch(batch: RunData) -> None:
        tables = schema.tables(batch, offset)
        add(tables)
        summary.records += len(batch.records)
        summary.frames += len(batch.frames)
        summary.topics = max(summary.topics, len(tables.topics))
        summary.batches += 1

    stream_run(src, on_batch, batch_ticks=batch_ticks)
