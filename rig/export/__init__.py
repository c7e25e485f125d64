"""Export of a recording to measurement-tool formats (``rig export``, docs/recording.md
"Export"): :mod:`rig.export.tables` turns a run (:func:`rig.recording.read_run`) into
columns, one table per tick topic plus the CAN bus log; :mod:`rig.export.mf4` writes
them as ASAM MDF 4 (asammdf), :mod:`rig.export.parquet` as Parquet files (pyarrow)."""

from rig.export.tables import CanLog, RunTables, TopicTable, run_tables, unit_of

__all__ = ["CanLog", "RunTables", "TopicTable", "run_tables", "unit_of"]
