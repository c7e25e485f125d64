"""``rig export`` in bounded memory: the recording is read twice in batches
(:func:`rig.recording.run_data.stream_run`, ``read_run``'s decoders): the first pass
decides the columns over the whole run (:class:`~rig.export.tables.TableSchema`), the
second lays each batch out and appends it to the MF4 (:class:`~rig.export.mf4.Mf4Stream`),
the Parquet files (:class:`~rig.export.parquet.ParquetStream`, a row group per batch) or
the CSV files (:class:`~rig.export.csv.CsvStream`).  Peak memory: one batch
(``batch_ticks`` records as objects and as columns) plus the writers' buffers, whatever
the length of the run."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from rig.export.tables import RunTables, TableSchema, clock_offset_ns
from rig.extras import EXPORT, require
from rig.recording.run_data import STREAM_BATCH_TICKS, RunData, stream_run

__all__ = ["STAGES", "WRITER_MODULES", "ExportSummary", "export_run", "require_writer"]

#: format -> (the module its writer needs, of the ``export`` extra; what it is called)
WRITER_MODULES: Final = {"mf4": ("asammdf", "MF4 export"),
                         "parquet": ("pyarrow", "Parquet export"),
                         "csv": ("pyarrow", "CSV export")}

#: the stages of an export, in order, as :attr:`ExportSummary.stage_s` names them:
#: ``scan`` the first pass (read, decode, decide the columns), ``read`` the second
#: pass's reading and decoding, ``columns`` laying the batches out as columns,
#: ``write`` handing them to the writer, ``finish`` the writer's last step (MF4: the
#: file is compressed and written; Parquet, CSV: the files are closed)
STAGES: Final = ("scan", "read", "columns", "write", "finish")


@dataclass
class ExportSummary:
    run: RunData                 # metadata, complete, stopped_at (no items)
    records: int = 0
    frames: int = 0
    topics: int = 0
    batches: int = 0
    skipped: list[str] = field(default_factory=list)
    #: wall seconds per stage (:data:`STAGES`)
    stage_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))


def export_run(src: str | Path, fmt: str, out: str | Path, *, comment: str = "",
               batch_ticks: int = STREAM_BATCH_TICKS) -> ExportSummary:
    """Export the recording ``src`` as ``fmt`` (``mf4``: the new file ``out``;
    ``parquet``, ``csv``: into the new, empty directory ``out``).  Raises
    :class:`rig.extras.MissingExtraError` before reading anything when the format's writer is
    not installed."""
    require_writer(fmt)
    schema = TableSchema()
    t = time.perf_counter()
    head = stream_run(src, schema.observe, batch_ticks=batch_ticks)
    offset = clock_offset_ns(head)
    summary = ExportSummary(head, skipped=schema.skipped)
    summary.stage_s["scan"] = time.perf_counter() - t
    if fmt == "mf4":
        from rig.export.mf4 import Mf4Stream

        mf4 = Mf4Stream((schema.t0_ns or 0) + offset, comment=comment)
        try:
            _stream(src, schema, offset, mf4.add, summary, batch_ticks)
            t = time.perf_counter()
            mf4.save(out)
            summary.stage_s["finish"] = time.perf_counter() - t
        finally:
            mf4.close()
    else:
        from rig.export.csv import CsvStream
        from rig.export.parquet import ParquetStream

        files = ParquetStream(out) if fmt == "parquet" else CsvStream(out)
        try:
            _stream(src, schema, offset, files.add, summary, batch_ticks)
        finally:
            t = time.perf_counter()
            files.close()
            summary.stage_s["finish"] = time.perf_counter() - t
    return summary


def require_writer(fmt: str) -> None:
    """Raise :class:`rig.extras.MissingExtraError` when ``fmt``'s writer is not installed."""
    module, what = WRITER_MODULES[fmt]
    require(module, EXPORT, what)


def _stream(src: str | Path, schema: TableSchema, offset: int,
            add: Callable[[RunTables], None],
            summary: ExportSummary, batch_ticks: int) -> None:
    stage_s = summary.stage_s

    def on_batch(batch: RunData) -> None:
        t0 = time.perf_counter()
        tables = schema.tables(batch, offset)
        t1 = time.perf_counter()
        add(tables)
        t2 = time.perf_counter()
        stage_s["columns"] += t1 - t0
        stage_s["write"] += t2 - t1
        summary.records += len(batch.records)
        summary.frames += len(batch.frames)
        summary.topics = max(summary.topics, len(tables.topics))
        summary.batches += 1

    t = time.perf_counter()
    stream_run(src, on_batch, batch_ticks=batch_ticks)
    stage_s["read"] = time.perf_counter() - t - stage_s["columns"] - stage_s["write"]
