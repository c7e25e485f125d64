"""``rig export``: MF4 (asammdf, python-can's MF4 reader) and Parquet (pyarrow, pandas)
round trips against :func:`rig.recording.read_run`, refusals, no partial output, and
``rig replay`` of an exported MF4 CAN log."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import can
import numpy as np
import pyarrow.parquet as pq
import pytest
from asammdf import MDF

from controller.artifact import load_design
from controller.config import default_config
from hil.stepped_run import record_emulated_run
from rig.cli import main
from rig.export import run_tables, unit_of
from rig.export.csv_files import CAN_CSV, csv_file
from rig.export.parquet import CAN_FILE, table_file
from rig.recording.run_data import RunData, read_run
from rig.recording.schema import SIGNAL_KEYS, TIMING_KEYS, TOPIC_SIGNALS, TOPIC_TIMING
from rig.replay import replay_log

pytestmark = pytest.mark.timeout(300)
CFG = default_config()


@pytest.fixture(scope="module")
def work() -> Any:
    with tempfile.TemporaryDirectory(prefix="test-export-") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def recording(work: Path, design_path: Path) -> Path:
    """0.4 s, armed, with a blending change (the internals change on the way)."""
    return record_emulated_run(work / "run.mcap", 0.4, cfg=CFG,
                               design_bytes=design_path.read_bytes(), seed=5,
                               commands={200: ("blending", 1)})


@pytest.fixture(scope="module")
def run(recording: Path) -> RunData:
    return read_run(recording)


@pytest.fixture(scope="module")
def mf4(recording: Path, work: Path) -> Path:
    out = work / "run.mf4"
    assert main(["export", str(recording), "--format", "mf4", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def parquet_dir(recording: Path, work: Path) -> Path:
    out = work / "parquet"
    assert main(["export", str(recording), "--format", "parquet", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def csv_dir(recording: Path, work: Path) -> Path:
    out = work / "csv"
    assert main(["export", str(recording), "--format", "csv", "--out", str(out)]) == 0
    return out


def _expected(run: RunData, key: str) -> np.ndarray:
    """``key`` of every tick record as read_run gives it (None -> NaN, list -> rows)."""
    vals = [r.data[key] for r in run.records]
    return np.array([[math.nan if x is None else x for x in v] if isinstance(v, list)
                     else (math.nan if v is None else v) for v in vals], dtype=np.float64)


def _numeric_keys(run: RunData) -> list[str]:
    return [k for k, v in run.records[0].data.items()
            if k != "tick" and not isinstance(v, str)
            and not (isinstance(v, list) and v and isinstance(v[0], str))]


def _frames(run: RunData) -> list[tuple[int, bytes, bool]]:
    return [(f.arbitration_id, f.data, f.is_rx) for f in run.frames]


def _t_s(run: RunData, t_ns: list[int]) -> np.ndarray:
    t0 = min(run.records[0].t_ns, run.frames[0].t_ns)
    return (np.array(t_ns, dtype=np.int64) - t0) * 1e-9


# ---------------------------------------------------------------------------- MF4


def test_mf4_can_log_reads_back_with_python_can(run: RunData, mf4: Path) -> None:
    with can.io.MF4Reader(str(mf4)) as reader:
        msgs = list(reader)
    assert len(msgs) == len(run.frames)
    # MF4Reader merges by timestamp; within a timestamp the file order is kept per group
    got = sorted(((m.arbitration_id, bytes(m.data), m.is_rx), round(m.timestamp, 5))
                 for m in msgs)
    t0 = msgs[0].timestamp - 0.0
    want = sorted(((f.arbitration_id, f.data, f.is_rx),
                   round(t0 + (f.t_ns - run.frames[0].t_ns) * 1e-9, 5)) for f in run.frames)
    assert got == want
    assert all(m.dlc == len(m.data) and not m.is_extended_id for m in msgs)


def test_mf4_bus_log_is_asam_bus_logging(run: RunData, mf4: Path) -> None:
    with MDF(str(mf4)) as mdf:
        frames = mdf.get("CAN_DataFrame")
        assert frames.samples.size == len(run.frames)
        names = frames.samples.dtype.names
        for field in ("ID", "DLC", "DataBytes", "Dir", "BusChannel"):
            assert f"CAN_DataFrame.{field}" in names
        ids = frames.samples["CAN_DataFrame.ID"].tolist()
        assert ids == [f.arbitration_id for f in run.frames]
        data = frames.samples["CAN_DataFrame.DataBytes"]
        dlc = frames.samples["CAN_DataFrame.DLC"]
        assert [bytes(d[:n]) for d, n in zip(data, dlc, strict=True)] == \
            [f.data for f in run.frames]
        assert (frames.samples["CAN_DataFrame.Dir"] == 0).tolist() == \
            [f.is_rx for f in run.frames]
        np.testing.assert_allclose(frames.timestamps, _t_s(run, [f.t_ns for f in run.frames]),
                                   atol=1e-9)
        # asammdf's own bus-log decoding with the DBC gives the signals of the frames
        decoded = mdf.extract_bus_logging({"CAN": [(str(Path("rig/wire/rig.dbc")), 0)]})
        names_decoded = {c.name for g in decoded.groups for c in g.channels}
        assert {"Rattlespace", "SpoolCommand", "ForceReference"} <= names_decoded
        decoded.close()


def test_mf4_signals_equal_read_run(run: RunData, mf4: Path) -> None:
    with MDF(str(mf4)) as mdf:
        groups = {g.channel_group.acq_name: i for i, g in enumerate(mdf.groups)}
        assert {TOPIC_SIGNALS, TOPIC_TIMING, "/controller/internals"} <= set(groups)
        t_s = _t_s(run, [r.t_ns for r in run.records])
        for key in _numeric_keys(run):
            topic = (TOPIC_SIGNALS if key in SIGNAL_KEYS else TOPIC_TIMING
                     if key in TIMING_KEYS else "/controller/internals")
            want = _expected(run, key)
            cols = [f"{key}[{i}]" for i in range(want.shape[1])] if want.ndim == 2 else [key]
            for j, name in enumerate(cols):
                sig = mdf.get(name, groups[topic])
                np.testing.assert_array_equal(
                    sig.samples.astype(np.float64), want[:, j] if want.ndim == 2 else want,
                    err_msg=name)
                np.testing.assert_allclose(sig.timestamps, t_s, atol=1e-9)
                assert sig.unit == unit_of(name)
        assert mdf.get("force_ref_n", groups[TOPIC_SIGNALS]).unit == "N"
        assert mdf.get("sprung_accel_mps2", groups[TOPIC_SIGNALS]).unit == "m/s^2"


# ---------------------------------------------------------------------------- Parquet


def test_parquet_tables_equal_read_run(run: RunData, parquet_dir: Path) -> None:
    tables = {t.topic: t for t in run_tables(run).topics}
    assert sorted(p.name for p in parquet_dir.iterdir()) == sorted(
        [CAN_FILE, *(table_file(t) for t in tables)])
    t_s = _t_s(run, [r.t_ns for r in run.records])
    for topic in tables:
        tab = pq.read_table(parquet_dir / table_file(topic))
        np.testing.assert_allclose(tab["t_s"].to_numpy(), t_s, atol=1e-12)
        assert tab["t_ns"].to_pylist() == [r.t_ns for r in run.records]
        assert tab["tick"].to_pylist() == [r.tick for r in run.records]
        for name in tab.column_names[3:]:
            key, _, idx = name.partition("[")
            want = _expected(run, key)
            if idx:
                want = want[:, int(idx.rstrip("]"))]
            np.testing.assert_array_equal(tab[name].to_numpy().astype(np.float64), want)
            unit = unit_of(name)
            meta = tab.schema.field(name).metadata
            assert (meta or {}).get(b"unit", b"").decode() == unit
    sig = pq.read_table(parquet_dir / table_file(TOPIC_SIGNALS))
    assert sig.schema.field("force_ref_n").metadata == {b"unit": b"N"}


def test_parquet_can_table_equals_the_frames(run: RunData, parquet_dir: Path) -> None:
    tab = pq.read_table(parquet_dir / CAN_FILE).to_pydict()
    assert list(zip(tab["id"], tab["data"], [d == "rx" for d in tab["direction"]],
                    strict=True)) == _frames(run)
    assert tab["dlc"] == [len(f.data) for f in run.frames]
    assert tab["t_ns"] == [f.t_ns for f in run.frames]


def test_parquet_reads_with_pandas(run: RunData, parquet_dir: Path) -> None:
    pd = pytest.importorskip("pandas")
    df = pd.read_parquet(parquet_dir / table_file(TOPIC_SIGNALS))
    np.testing.assert_array_equal(df["force_ref_n"].to_numpy(), _expected(run, "force_ref_n"))
    frames = pd.read_parquet(parquet_dir / CAN_FILE)
    assert frames["id"].tolist() == [f.arbitration_id for f in run.frames]


def test_csv_tables_equal_read_run(run: RunData, csv_dir: Path) -> None:
    pd = pytest.importorskip("pandas")
    tables = {t.topic: t for t in run_tables(run).topics}
    assert sorted(p.name for p in csv_dir.iterdir()) == sorted(
        [CAN_CSV, *(csv_file(t) for t in tables)])
    for topic, table in tables.items():
        df = pd.read_csv(csv_dir / csv_file(topic), engine="pyarrow")  # exact floats
        assert list(df.columns) == ["t_s", "t_ns", "tick", *table.columns]
        assert df["t_ns"].tolist() == [r.t_ns for r in run.records]
        assert df["tick"].tolist() == [r.tick for r in run.records]
        for name in table.columns:
            key, _, idx = name.partition("[")
            want = _expected(run, key)
            if idx:
                want = want[:, int(idx.rstrip("]"))]
            np.testing.assert_array_equal(df[name].to_numpy(np.float64), want)


def test_csv_can_table_equals_the_frames(run: RunData, csv_dir: Path) -> None:
    pd = pytest.importorskip("pandas")
    df = pd.read_csv(csv_dir / CAN_CSV, dtype={"data": str}, keep_default_na=False)
    assert list(zip(df["id"], [bytes.fromhex(d) for d in df["data"]],
                    [d == "rx" for d in df["direction"]], strict=True)) == _frames(run)
    assert df["dlc"].tolist() == [len(f.data) for f in run.frames]
    assert df["t_ns"].tolist() == [f.t_ns for f in run.frames]
    assert df["error_frame"].tolist() == [f.is_error_frame for f in run.frames]


# ---------------------------------------------------------------------------- refusals


def test_existing_output_needs_force_and_failure_leaves_nothing(
        recording: Path, mf4: Path, parquet_dir: Path, work: Path,
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    before = mf4.read_bytes()
    assert main(["export", str(recording), "--format", "mf4", "--out", str(mf4)]) == 2
    assert "exists: add --force" in capsys.readouterr().err
    assert main(["export", str(recording), "--format", "parquet",
                 "--out", str(parquet_dir)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["export", str(recording), "--format", "mf4", "--out",
                 str(work / "x.mdf")]) == 2
    assert ".mf4 file" in capsys.readouterr().err
    assert main(["export", str(work / "none.mcap"), "--format", "mf4", "--out",
                 str(work / "y.mf4")]) == 2
    assert main(["export", str(recording), "--format", "xlsx", "--out", "z"]) == 2
    capsys.readouterr()
    not_mcap = work / "notes.mcap"
    not_mcap.write_text("hello")
    assert main(["export", str(not_mcap), "--format", "mf4", "--out",
                 str(work / "n.mf4")]) == 2
    err = capsys.readouterr().err
    assert "not an MCAP file" in err and len(err.strip().splitlines()) == 1

    import rig.export.mf4 as mf4_mod

    def boom(*_a: Any, **_k: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mf4_mod.MDF, "save", boom)
    assert main(["export", str(recording), "--format", "mf4", "--out", str(mf4),
                 "--force"]) == 2
    assert "No space left" in capsys.readouterr().err
    assert mf4.read_bytes() == before
    assert not [p for p in work.iterdir() if ".partial-" in p.name]


# ---------------------------------------------------------------------------- replay


def test_replay_of_the_mf4_log_equals_the_asc_equivalent(run: RunData, mf4: Path,
                                                        work: Path, design_path: Path) -> None:
    asc = work / "same.asc"
    with can.io.MF4Reader(str(mf4)) as reader, can.Logger(str(asc)) as logger:
        for m in reader:
            logger.on_message_received(m)
    design = load_design(design_path)
    res_mf4 = replay_log(mf4, CFG, design)
    res_asc = replay_log(asc, CFG, design)
    assert res_mf4.ticks == res_asc.ticks >= len(run.records)
    assert res_mf4.rx_frames_fed == res_asc.rx_frames_fed == sum(f.is_rx for f in run.frames)
    np.testing.assert_array_equal(res_mf4.force_ref_n, res_asc.force_ref_n)
    # and the bank's force reference is the recorded one where the loop was not yet armed
    recorded = _expected(run, "force_ref_n")
    n = len(recorded)
    np.testing.assert_array_equal(res_mf4.force_ref_n[:n], recorded)


# ---------------------------------------------------------------------------- kinds


def test_column_kinds_of_every_value_type() -> None:
    """The kind and dtype of a field over its values: integers and booleans int64,
    numbers with a float or a missing value float64 (NaN), int and float subclasses
    (numpy scalars, enums) as numbers, lists one column per element (a missing list
    NaN), text, ragged lists and mixed lists left out."""
    import enum

    from rig.recording.run_data import TickRecord

    class Mode(enum.IntEnum):
        A = 3

    fields: dict[str, list[Any]] = {
        "count": [1, 2, True], "level": [1, None, 3], "gain": [1, 2.5, 3],
        "np_x": [np.float64(0.5), 1.0, 2], "mode": [Mode.A, 1, 2],
        "pair": [[1, 2], [3, 4], [5, 6]], "pair_f": [[1, 2.5], None, [5, 6]],
        "ragged": [[1], [1, 2], [3]], "text": ["a", "b", "c"], "mixed": [[1, 2], 3, [4, 5]],
        "text_list": [["a"], ["b"], ["c"]],
    }
    records = [TickRecord(i, 1000 * i, i, {"tick": i, **{k: v[i] for k, v in fields.items()}})
               for i in range(3)]
    tables = run_tables(RunData(records=records))
    cols = {name: col for t in tables.topics for name, col in t.columns.items()}
    assert {n: str(c.dtype) for n, c in cols.items()} == {
        "count": "int64", "level": "float64", "gain": "float64", "np_x": "float64",
        "mode": "float64", "pair[0]": "int64", "pair[1]": "int64", "pair_f[0]": "float64",
        "pair_f[1]": "float64"}
    assert sorted(tables.skipped) == ["mixed", "ragged", "text", "text_list"]
    assert np.isnan(cols["level"][1]) and np.isnan(cols["pair_f[1]"][1])
    assert cols["count"].tolist() == [1, 2, 1] and cols["mode"].tolist() == [3.0, 1.0, 2.0]


# ---------------------------------------------------------------------------- batches


def _exports(recording: Path, work: Path, batch_ticks: int
             ) -> tuple[tuple[Path, Path, Path], int]:
    """The three exports of ``recording`` in batches of ``batch_ticks`` ticks, and the
    MF4 export's passes over the recording."""
    from rig.export.stream import export_run

    mf4, pq_dir, csv_dir = (work / f"b{batch_ticks}.mf4", work / f"b{batch_ticks}",
                            work / f"b{batch_ticks}-csv")
    pq_dir.mkdir()
    csv_dir.mkdir()
    summary = export_run(recording, "mf4", mf4, batch_ticks=batch_ticks)
    assert summary.batches > (batch_ticks < 10**9)
    for fmt, out in (("parquet", pq_dir), ("csv", csv_dir)):
        assert export_run(recording, fmt, out, batch_ticks=batch_ticks).passes == \
            summary.passes
    return (mf4, pq_dir, csv_dir), summary.passes


def _assert_same_exports(one: tuple[Path, Path, Path], many: tuple[Path, Path, Path]
                         ) -> None:
    """Two exports of one recording are the same: CSV byte for byte, Parquet and MF4
    value for value (bit for bit, NaN too) with the same schemas, units and groups."""
    (one_mf4, one_pq, one_csv), (many_mf4, many_pq, many_csv) = one, many
    assert sorted(p.name for p in one_csv.iterdir()) == sorted(
        p.name for p in many_csv.iterdir())
    for path in one_csv.iterdir():
        assert path.read_bytes() == (many_csv / path.name).read_bytes(), path.name
    assert pq.ParquetFile(many_pq / table_file(TOPIC_SIGNALS)).num_row_groups > 1
    assert sorted(p.name for p in one_pq.iterdir()) == sorted(
        p.name for p in many_pq.iterdir())
    for name in sorted(p.name for p in one_pq.iterdir()):
        a, b = pq.read_table(one_pq / name), pq.read_table(many_pq / name)
        assert a.schema.equals(b.schema, check_metadata=True), name
        for col in a.column_names:      # NaN too: bit for bit
            x, y = a[col].to_numpy(), b[col].to_numpy()
            assert (x.tobytes() == y.tobytes() if x.dtype.kind in "fiub"
                    else x.tolist() == y.tolist()), (name, col)
    with MDF(str(one_mf4)) as m1, MDF(str(many_mf4)) as m2:
        assert m1.header.start_time == m2.header.start_time
        assert len(m1.groups) == len(m2.groups)
        for gi, group in enumerate(m1.groups):
            assert m2.groups[gi].channel_group.acq_name == group.channel_group.acq_name
            assert [c.name for c in m2.groups[gi].channels] == [c.name for c in
                                                                 group.channels]
            for ci, ch in enumerate(group.channels):
                s1, s2 = m1.get(ch.name, gi, ci), m2.get(ch.name, gi, ci)
                assert s1.samples.dtype == s2.samples.dtype, ch.name
                assert s1.samples.tobytes() == s2.samples.tobytes(), ch.name
                assert s1.timestamps.tobytes() == s2.timestamps.tobytes(), ch.name
                assert s1.unit == s2.unit


def test_export_in_batches_equals_one_batch(recording: Path, work: Path) -> None:
    """The loop's records keep one layout for the whole run (a blending change on the
    way): one reading of the recording, in batches the same output as in one."""
    one, passes_one = _exports(recording, work, 10**9)
    many, passes_many = _exports(recording, work, 37)
    assert passes_one == passes_many == 1
    _assert_same_exports(one, many)


def test_a_layout_that_changes_mid_run_takes_a_second_pass(tmp_path: Path) -> None:
    """Records of a generic caller whose fields change after the first batch (a key
    that first appears later, an integer field that turns float, a list that turns
    text): what the first batches wrote is discarded and the second pass writes the
    run's layout -- the same output as one batch gives."""
    from dataclasses import replace

    from rig.recording.recorder import RunRecorder

    path = tmp_path / "generic.mcap"
    cfg = replace(CFG.recording, chunk_bytes=2048, batch_ticks=1)
    with RunRecorder(path, cfg, config_toml="", design_bytes=None, metadata={},
                     poll_s=0.001) as rec:
        for k in range(120):
            t_ns = 1_000_000 * k + 5_000_000_000
            rec.can_frame(t_ns, k, 0x101, bytes([k % 256, 1, 2]), is_rx=True)
            record: dict[str, Any] = {"tick": k, "rattlespace_m": 1e-3 * k,
                                      "weight_set": 1 if k < 70 else 1.5,
                                      "u_model": [float(k), 2.0] if k < 90 else "none",
                                      "wake_late_s": 2e-5}
            if k >= 50:
                record["stop_contact_s"] = 0.001 * k
            rec.tick(t_ns, record)
    one, passes_one = _exports(path, tmp_path, 10**9)
    many, passes_many = _exports(path, tmp_path, 10)
    assert (passes_one, passes_many) == (1, 2)
    _assert_same_exports(one, many)
    table = pq.read_table(many[1] / table_file("/controller/internals"))
    assert table.schema.field("weight_set").type == "double"
    assert "u_model[0]" not in table.column_names
    assert np.isnan(table["stop_contact_s"].to_numpy()[:50]).all()
