"""``rig export`` in bounded memory and, as a rule, one reading of the recording
(:func:`rig.recording.run_data.stream_run`, ``read_run``'s decoders, in batches): each
batch is observed (:meth:`~rig.export.tables.TableSchema.observe`: the columns and their
dtypes as the run so far decides them), laid out and appended to the MF4
(:class:`~rig.export.mf4.Mf4Stream`), the Parquet files
(:class:`~rig.export.parquet.ParquetStream`, a row group per batch) or the CSV files
(:class:`~rig.export.csv_files.CsvStream`).  The columns of a run are decided over all of its
records (an integer field ``int64`` only when every record has one ...), so the output
is the run's only when the layout (:meth:`~rig.export.tables.TableSchema.layout`) the
first batch decides holds to the end, as it does for the loop's records (one tick
layout for the whole run).  When a later batch changes it (a field that first appears,
or first misses a value, after the first batch: records of a generic caller), what was
written is discarded and a second pass writes every batch with the layout of the whole
run; the output is the same either way (:attr:`ExportSummary.passes` says which).
Peak memory: one batch (``batch_ticks`` records as objects and as columns) plus the
writers' buffers, whatever the length of the run."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final

from rig.export.tables import RunTables, TableSchema, clock_offset_ns
from rig.extras import EXPORT, require
from rig.recording.run_data import STREAM_BATCH_TICKS, RunData, stream_run

if TYPE_CHECKING:            # the writers import asammdf / pyarrow: when they write
    from rig.export.csv_files import CsvStream
    from rig.export.mf4 import Mf4Stream
    from rig.export.parquet import ParquetStream

__all__ = ["STAGES", "WRITER_MODULES", "ExportSummary", "export_run", "require_writer"]

#: format -> (the module its writer needs, of the ``export`` extra; what it is called)
WRITER_MODULES: Final = {"mf4": ("asammdf", "MF4 export"),
                         "parquet": ("pyarrow", "Parquet export"),
                         "csv": ("pyarrow", "CSV export")}

#: the stages of an export, as :attr:`ExportSummary.stage_s` names them: ``scan``
#: deciding the columns (observing each batch), ``read`` reading and decoding the
#: recording (both passes when there are two), ``columns`` laying the batches out as
#: columns, ``write`` handing them to the writer, ``finish`` the writer's last step (MF4:
#: the file is compressed and written; Parquet, CSV: the files are closed)
STAGES: Final = ("scan", "read", "columns", "write", "finish")


@dataclass
class ExportSummary:
    run: RunData                 # metadata, complete, stopped_at (no items)
    records: int = 0
    frames: int = 0
    topics: int = 0
    batches: int = 0
    #: readings of the recording: 1, or 2 when the layout changed after the first batch
    passes: int = 1
    skipped: list[str] = field(default_factory=list)
    #: wall seconds per stage (:data:`STAGES`)
    stage_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))


class _Output:
    """The writer of one export: the MF4 is made at the first batch (its header takes
    the run's start time), the Parquet / CSV files at theirs; :meth:`discard` drops
    everything written (the second pass starts over)."""

    def __init__(self, fmt: str, out: Path, comment: str) -> None:
        self.fmt, self.out, self.comment = fmt, out, comment
        self._mf4: Mf4Stream | None = None
        self._files: ParquetStream | CsvStream | None = None
        self._open_files()

    def _open_files(self) -> None:
        if self.fmt == "parquet":
            from rig.export.parquet import ParquetStream

            self._files = ParquetStream(self.out)
        elif self.fmt == "csv":
            from rig.export.csv_files import CsvStream

            self._files = CsvStream(self.out)

    def add(self, tables: RunTables) -> None:
        if self._files is not None:
            self._files.add(tables)
            return
        if self._mf4 is None:
            self._mf4 = self._new_mf4(tables.start_wall_ns)
        self._mf4.add(tables)

    def _new_mf4(self, start_wall_ns: int) -> Mf4Stream:
        from rig.export.mf4 import Mf4Stream

        return Mf4Stream(start_wall_ns, comment=self.comment)

    def finish(self, start_wall_ns: int) -> None:
        """Write the MF4 (``start_wall_ns``: its start when no batch came) or close the
        files."""
        if self._files is not None:
            self._files.close()
            self._files = None
            return
        if self._mf4 is None:
            self._mf4 = self._new_mf4(start_wall_ns)
        self._mf4.save(self.out)

    def discard(self) -> None:
        if self._files is not None:
            for path in self._files.close():
                path.unlink(missing_ok=True)
            self._open_files()
        elif self._mf4 is not None:
            self._mf4.close()
            self._mf4 = None

    def close(self) -> None:
        if self._files is not None:
            self._files.close()
        if self._mf4 is not None:
            self._mf4.close()


def export_run(src: str | Path, fmt: str, out: str | Path, *, comment: str = "",
               batch_ticks: int = STREAM_BATCH_TICKS) -> ExportSummary:
    """Export the recording ``src`` as ``fmt`` (``mf4``: the new file ``out``;
    ``parquet``, ``csv``: into the new, empty directory ``out``).  Raises
    :class:`rig.extras.MissingExtraError` before reading anything when the format's
    writer is not installed."""
    require_writer(fmt)
    output = _Output(fmt, Path(out), comment)
    try:
        summary = _export(src, output, batch_ticks)
    finally:
        output.close()
    return summary


def require_writer(fmt: str) -> None:
    """Raise :class:`rig.extras.MissingExtraError` when ``fmt``'s writer is not installed."""
    module, what = WRITER_MODULES[fmt]
    require(module, EXPORT, what)


class _Pass:
    """One reading of the recording that writes each batch with ``schema``; when
    ``observe``, each batch is observed first and writing stops (:attr:`stale`) once
    the layout differs from the one the first batch decided."""

    def __init__(self, schema: TableSchema, output: _Output, summary: ExportSummary, *,
                 observe: bool, offset_ns: int | None = None) -> None:
        self.schema, self.output, self.summary = schema, output, summary
        self.observe = observe
        self.offset_ns = offset_ns
        self.layout: tuple[object, ...] | None = None
        self.stale = False

    def __call__(self, batch: RunData) -> None:
        stage_s = self.summary.stage_s
        t0 = time.perf_counter()
        if self.observe:
            self.schema.observe(batch)
            layout = self.schema.layout()
            if self.layout is None:
                self.layout = layout
                self.offset_ns = clock_offset_ns(batch)
            elif layout != self.layout:
                self.stale = True
            stage_s["scan"] += time.perf_counter() - t0
            if self.stale:
                return
        t1 = time.perf_counter()
        tables = self.schema.tables(batch, self.offset_ns or 0)
        t2 = time.perf_counter()
        self.output.add(tables)
        stage_s["columns"] += t2 - t1
        stage_s["write"] += time.perf_counter() - t2
        summary = self.summary
        summary.records += len(batch.records)
        summary.frames += len(batch.frames)
        summary.topics = max(summary.topics, len(tables.topics))
        summary.batches += 1

    def read(self, src: str | Path, batch_ticks: int) -> RunData:
        stage_s = self.summary.stage_s
        before = sum(stage_s[s] for s in ("scan", "columns", "write"))
        t = time.perf_counter()
        head = stream_run(src, self, batch_ticks=batch_ticks)
        spent = sum(stage_s[s] for s in ("scan", "columns", "write")) - before
        stage_s["read"] += time.perf_counter() - t - spent
        return head


def _export(src: str | Path, output: _Output, batch_ticks: int) -> ExportSummary:
    schema = TableSchema()
    summary = ExportSummary(RunData())
    first = _Pass(schema, output, summary, observe=True)
    summary.run = head = first.read(src, batch_ticks)
    offset_ns = clock_offset_ns(head)
    if first.stale or (first.offset_ns is not None and first.offset_ns != offset_ns):
        # the first batches were written with a layout the run did not keep: again,
        # every batch with the run's (the schema has now observed all of them)
        output.discard()
        summary.records = summary.frames = summary.topics = summary.batches = 0
        summary.passes = 2
        _Pass(schema, output, summary, observe=False, offset_ns=offset_ns).read(
            src, batch_ticks)
    summary.skipped = schema.skipped
    t = time.perf_counter()
    output.finish((schema.t0_ns or 0) + offset_ns)
    summary.stage_s["finish"] = time.perf_counter() - t
    return summary
