"""Replay: bit-exact re-run of a recorded run, other-design comparison, candump logs,
truncated / corrupt / foreign files, error frames and bus exceptions (rig/replay/,
docs/replay.md).

The recordings are produced here by the real loop, tick-stepped against the emulated
rig (hil.node.RigNode) on a python-can virtual bus with the RunRecorder on
(hil.stepped_run.record_emulated_run).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer

from controller.artifact import load_design, save_design
from controller.config import default_config
from controller.design import design_bank
from controller.runtime.bank import BankRuntime
from hil.stepped_run import record_emulated_run
from rig.cli import main as rig_main
from rig.recording.recorder import read_run
from rig.recording.schema import RECORDING_FORMAT_VERSION
from rig.replay import (
    LogReplayBus,
    McapReplayBus,
    RecordingError,
    load_recorded_run,
    replay_log,
    replay_recording,
)
from rig.report import load_series
from rig.service.assembly import LoopSettings
from rig.wire.protocol import (
    FAULT_REPORT_ID,
    SENSOR_DATA,
    SENSOR_DATA_ID,
    VALVE_COMMAND,
    VALVE_COMMAND_ID,
    DecodeStatus,
    SensorData,
    ValveCommand,
)
from tests.support.mcap_edit import chunk_spans
from tests.support.mcap_reference import items_of_run, reference_items

pytestmark = pytest.mark.timeout(300)
CFG = default_config()
#: operator commands of the main recording: disarm, blending change, re-arm, then an
#: overrun streak latches FAULT, reset, re-arm; the run ends with a shutdown
COMMANDS: dict[int, tuple[str, Any]] = {
    400: ("disarm", None), 450: ("blending", 1), 500: ("arm", None),
    900: ("reset", None), 950: ("arm", None)}
LATE = {k: 900_000 for k in range(700, 707)}   # > overrun threshold, streak of 7


@pytest.fixture(scope="module")
def work() -> Any:
    with tempfile.TemporaryDirectory(prefix="test-replay-") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def design_blob(design_path: Path) -> bytes:
    return design_path.read_bytes()


@pytest.fixture(scope="module")
def recording(work: Path, design_blob: bytes) -> Path:
    """1.2 s with commands, a latched fault, reset and shutdown."""
    return record_emulated_run(work / "run.mcap", 1.2, cfg=CFG, design_bytes=design_blob,
                               commands=COMMANDS, late_ticks=LATE)


@pytest.fixture(scope="module")
def plain_recording(work: Path, design_blob: bytes) -> Path:
    """0.8 s, armed once, no fault: every tick steps the bank with the frame of the tick."""
    return record_emulated_run(work / "plain.mcap", 0.8, cfg=CFG, design_bytes=design_blob,
                               seed=3)


# ---------------------------------------------------------------------------- bit exact


def test_replay_reproduces_the_recorded_frames_bit_for_bit(recording: Path) -> None:
    res = replay_recording(recording)
    run = read_run(recording)     # checked against the mcap library's reader (below)
    tx = [(f.tick, f.arbitration_id, f.data) for f in run.frames if not f.is_rx]
    assert res.same_controller and res.bit_exact, res.summary()
    assert res.tx_frames_recorded == len(tx) == res.tx_frames_compared
    assert res.tx_frames_mismatched == 0 and res.first_mismatch is None
    assert res.max_abs_command_diff == 0.0 and res.max_abs_force_ref_diff_n == 0.0
    assert res.valve_frames_compared == sum(1 for t in tx if t[1] == VALVE_COMMAND_ID)
    # + the arm at 0.1 s
    assert res.commands_reapplied == len(COMMANDS) + 1 and res.commands_outcome_differs == 0
    # the run really exercised arming, the overrun fault and the shutdown
    assert res.faults == ["OVERRUN_STREAK"] and res.final_state == "STOPPING"
    enabled = [ValveCommand() for t in tx if t[1] == VALVE_COMMAND_ID]
    for v, t in zip(enabled, [t for t in tx if t[1] == VALVE_COMMAND_ID], strict=True):
        assert VALVE_COMMAND.decode(bytearray(t[2]), v) is DecodeStatus.OK
    assert sum(v.enable for v in enabled) > 300
    rec_spool = np.array([r.data["spool_cmd"] for r in run.records])
    np.testing.assert_array_equal(res.spool_cmd, rec_spool)


def test_a_changed_sensor_frame_is_detected(recording: Path) -> None:
    """The comparison can fail: one altered rattlespace reading changes the commands."""
    run = load_recorded_run(recording)
    k = next(i for i, f in enumerate(run.rx) if f[2] == SENSOR_DATA_ID and f[0] == 600)
    tick, t_ns, fid, data, flags = run.rx[k]
    sd = SensorData()
    assert SENSOR_DATA.decode(bytearray(data), sd) is DecodeStatus.OK
    buf = bytearray(8)
    SENSOR_DATA.encode(buf, sd.counter, sd.sensor_status, sd.rattlespace_m + 0.004,
                       sd.load_cell_force_n, sd.sprung_accel_mps2)
    run.rx[k] = (tick, t_ns, fid, bytes(buf), flags)
    res = replay_recording(recording, run=run)
    assert not res.bit_exact
    assert res.tx_frames_mismatched > 0 and res.max_abs_command_diff > 0
    assert res.first_mismatch is not None and res.first_mismatch["replayed"]["tick"] >= 600


def test_cli_replay_json(recording: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert rig_main(["replay", str(recording), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["max_abs_command_diff"] == 0 and out["bit_exact"] is True
    assert out["tx_frames_compared"] == out["tx_frames_recorded"] > 1000
    assert out["realtime_factor"] > 1


def test_replay_bus_is_a_busabc_releasing_frames_by_tick(plain_recording: Path) -> None:
    run = load_recorded_run(plain_recording)
    bus = McapReplayBus(run.rx)
    assert isinstance(bus, can.BusABC)
    assert bus.recv(0) is None                    # nothing released before tick 0
    bus.advance(0)
    got = []
    while (m := bus.recv(0)) is not None:
        got.append(m)
    assert [(0, m.arbitration_id, bytes(m.data)) for m in got] == \
        [(f[0], f[2], f[3]) for f in run.rx if f[0] == 0]
    bus.release_all()
    assert sum(1 for _ in iter(lambda: bus.recv(0), None)) == len(run.rx) - len(got)
    bus.shutdown()


# ---------------------------------------------------------------------------- other design


def _bank_alone(run: Any, design: Any, cfg: Any) -> np.ndarray:
    """Second implementation: BankRuntime stepped directly on the decoded sensor frames
    (one per tick, no resets in the plain recording), with the road preview of the
    travel schedule (and of the governed comfort set) taken from the RoadPreview frames
    by their lead (the i-th RoadPreview holds the road velocity of rig tick i + lead;
    SensorData i is checked against the road of ticks i + 1 .. i + H when all of them
    have come)."""
    from controller.road_preview import road_preview
    from rig.wire.protocol import ROAD_PREVIEW, ROAD_PREVIEW_ID, RoadPreview

    rt = BankRuntime(design, weight_set=cfg.design.weight_set, cfg=cfg)
    pv = road_preview(cfg)     # any weight set: a fixed one never calls (rt decides)
    sd, rp = SensorData(), RoadPreview()
    ahead: dict[int, float] = {}
    i = previews = -1
    live = False
    out = []
    for _tick, _, fid, data, _flags in run.rx:
        if fid == SENSOR_DATA_ID:
            assert SENSOR_DATA.decode(bytearray(data), sd) is DecodeStatus.OK
            i += 1
            if pv is not None:
                window = [ahead.get(j) for j in range(i + 1, i + 1 + pv.horizon_ticks)]
                if all(v is not None for v in window) is not live:
                    live = not live
                    rt.use_preview_schedule(live)
                if live:
                    rt.check_road_preview(pv, sd.rattlespace_m, sd.load_cell_force_n,
                                          np.array(window), 0)
            out.append(rt.step(sd.rattlespace_m, sd.sprung_accel_mps2, sd.load_cell_force_n))
        elif fid == ROAD_PREVIEW_ID:
            assert ROAD_PREVIEW.decode(bytearray(data), rp) is DecodeStatus.OK
            previews += 1
            ahead[previews + rp.preview_lead] = rp.road_velocity_mps
    return np.array(out)


def test_other_design_is_compared_open_loop_and_written(plain_recording: Path,
                                                        work: Path, design_path: Path) -> None:
    cfg2 = CFG.replace(design={"weight_set": 2})
    design2 = design_bank(cfg2)
    p2 = work / "design2.npz"
    save_design(design2, p2)
    out = work / "other.mcap"
    res = replay_recording(plain_recording, cfg=cfg2, design=load_design(p2, cfg2),
                           design_bytes=p2.read_bytes(), out=out)
    assert not res.same_controller and not res.bit_exact
    c = res.comparison
    assert c is not None and "open loop" in c["note"]
    assert any("open loop" in n for n in res.notes)
    assert c["force_ref_rms_difference_n"] > 0.01 * c["force_ref_rms_recorded_n"] > 0
    run = load_recorded_run(plain_recording)
    # the replayed bank output equals the bank run alone on the same sensor data
    np.testing.assert_array_equal(res.force_ref_n, _bank_alone(run, design2, cfg2))
    # ... and the recorded one equals the recorded design run alone
    np.testing.assert_array_equal(run.force_ref_n,
                                  _bank_alone(run, load_design(design_path), CFG))
    new = read_run(out)
    assert new.complete
    meta = new.metadata["rig"]
    assert meta["replay_of"] == str(plain_recording) and meta["open_loop"] == "true"
    np.testing.assert_array_equal([r.data["force_ref_n"] for r in new.records],
                                  res.force_ref_n)
    # the new recording is itself replayable, bit for bit, with its own design
    again = replay_recording(out)
    assert again.bit_exact, again.summary()


def test_cli_other_design(plain_recording: Path, work: Path,
                          capsys: pytest.CaptureFixture[str]) -> None:
    cfg2 = CFG.replace(design={"weight_set": 2})
    p2 = work / "design2-cli.npz"
    save_design(design_bank(cfg2), p2)
    toml = work / "cfg2.toml"
    from controller.config import config_to_toml

    toml.write_text(config_to_toml(cfg2))
    rc = rig_main(["replay", str(plain_recording), "--design", str(p2), "--config", str(toml),
                   "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["same_controller"] is False
    assert out["comparison"]["force_ref_rms_replayed_n"] > 0


# ---------------------------------------------------------------------------- candump logs


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_candump_log_replay_matches_the_recording(plain_recording: Path, work: Path,
                                                  suffix: str, design_path: Path) -> None:
    run = load_recorded_run(plain_recording)
    path = work / f"plain{suffix}"
    with can.Logger(str(path)) as logger:
        for _tick, t_ns, fid, data, _flags in run.rx:
            logger.on_message_received(can.Message(
                timestamp=t_ns * 1e-9, arbitration_id=fid, data=data, is_extended_id=False))
        for tick, fid, data, _flags in run.tx[:50]:     # the controller's own frames: filtered
            logger.on_message_received(can.Message(
                timestamp=(1_000_000_000 + tick * 1_000_000 + 300_000) * 1e-9,
                arbitration_id=fid, data=data, is_extended_id=False))
    design = load_design(design_path)
    res = replay_log(path, CFG, design)
    assert res.kind == "log" and res.ticks == run.tick.size
    assert res.rx_frames_fed == len(run.rx)
    # INACTIVE all along (a log has no commands), but the bank's force reference is the
    # recorded one: the same sensor frames reached the same loop code at the same ticks
    np.testing.assert_array_equal(res.force_ref_n, run.force_ref_n)
    assert res.valve_enable.sum() == 0 and res.faults == []
    assert any("open loop" in n for n in res.notes)


def test_log_bus_filters_and_rejects_unknown_formats(work: Path) -> None:
    p = work / "mixed.log"
    with can.Logger(str(p)) as logger:
        for i, fid in enumerate((0x100, 0x080, 0x555, 0x200)):
            logger.on_message_received(can.Message(timestamp=1.0 + i * 1e-3,
                                                   arbitration_id=fid, data=bytes(8),
                                                   is_extended_id=False))
    bus = LogReplayBus(p)
    bus.advance_time(10.0)
    ids = [m.arbitration_id for m in iter(lambda: bus.recv(0), None)]
    assert ids == [0x100, 0x200] and bus.filtered == 2
    bus.shutdown()
    bad = work / "x.trc2"
    bad.write_text("nope")
    with pytest.raises(RecordingError, match="unknown log format"):
        LogReplayBus(bad)
    garbage = work / "garbage.blf"
    garbage.write_bytes(b"\x00" * 64)
    with pytest.raises(RecordingError, match=r"not a readable \.blf log"):
        LogReplayBus(garbage)


# ---------------------------------------------------------------------------- bad files


def test_the_recording_reads_the_same_with_the_mcap_library(recording: Path) -> None:
    """The one production reader (read_run on the scanner replay uses) against an
    independent one (the mcap library + json + the channels' schemas) over a run of the
    real loop: packed tick records with the bank's internals, commands, a fault."""
    run = read_run(recording)
    ref = reference_items([recording])
    assert run.complete and items_of_run(run) == ref
    assert sum(1 for item in ref if item[0] == "record") > 1000
    assert {item[3] for item in ref if item[0] == "event"} >= {"command", "lifecycle"}
    replayed = load_recorded_run(recording)        # and what replay decodes of it
    np.testing.assert_array_equal(replayed.tick, [r.tick for r in run.records])
    assert replayed.tx == [(f.tick, f.arbitration_id, f.data, 0)
                           for f in run.frames if not f.is_rx]


def _inside_a_chunk(recording: Path, frac: float) -> int:
    """A byte in the middle of the chunk at ``frac`` of the recording's chunks (not at a
    fraction of the file: the design attachment before the chunks is most of a file,
    0.1 MB for a one-layer bank, 1.8 MB for the built-in layered one)."""
    chunks = chunk_spans(recording)
    assert len(chunks) >= 3, len(chunks)        # one before the middle one, one after
    start, end = chunks[max(1, min(len(chunks) - 2, int(len(chunks) * frac)))]
    return (start + end) // 2


def test_truncated_recording_replays_to_its_last_complete_chunk(recording: Path,
                                                                 work: Path) -> None:
    full = load_recorded_run(recording)
    data = recording.read_bytes()
    cut = work / "cut.mcap"
    cut.write_bytes(data[: _inside_a_chunk(recording, 0.6)])
    res = replay_recording(cut)
    assert not res.complete and "truncated at byte" in str(res.stopped_at)
    assert any("last complete chunk" in n for n in res.notes)
    assert 0 < res.ticks < full.tick.size
    # the prefix that was read replays bit for bit
    assert res.bit_exact, res.summary()
    assert res.tx_frames_compared == res.tx_frames_recorded > 0


@settings(max_examples=12, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.0, 1.0))
def test_any_truncation_is_a_prefix_or_a_clear_error(recording: Path, frac: float) -> None:
    data = recording.read_bytes()
    full = load_recorded_run(recording)
    n = int(len(data) * frac)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "t.mcap"
        p.write_bytes(data[:n])
        try:
            run = load_recorded_run(p)
        except RecordingError as exc:
            msg = str(exc)
            assert "not an MCAP" in msg or "nothing to replay" in msg or "missing" in msg
            return
    assert run.complete == (n == len(data)), run.stopped_at   # a cut is always noticed
    assert run.complete or str(p) in str(run.stopped_at)
    k = run.tick.size
    np.testing.assert_array_equal(run.tick, full.tick[:k])
    assert run.tx == full.tx[: len(run.tx)] and run.rx == full.rx[: len(run.rx)]
    if k:
        res = replay_recording(recording, run=run)
        assert res.bit_exact, res.summary()


def test_corrupt_chunk_is_named_and_earlier_chunks_replay(recording: Path, work: Path) -> None:
    data = bytearray(recording.read_bytes())
    mid = _inside_a_chunk(recording, 0.5)
    data[mid:mid + 64] = bytes(64)
    p = work / "corrupt.mcap"
    p.write_bytes(bytes(data))
    run = load_recorded_run(p)
    assert not run.complete and "corrupt Chunk record at byte" in str(run.stopped_at)
    res = replay_recording(p, run=run)
    assert res.ticks > 0 and res.bit_exact, res.summary()


def _mcap(path: Path, topics: list[str], *, library: str, metadata: dict[str, str] | None
          ) -> Path:
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library=library)
        if metadata is not None:
            w.add_metadata("rig", metadata)
        sid = w.register_schema("x", "jsonschema", b"{}")
        for t in topics:
            ch = w.register_channel(t, "json", sid)
            w.add_message(ch, 1, b'{"tick":0,"t_ns":0}', 1)
        w.finish()
    return path


@pytest.mark.parametrize(("make", "match"), [
    (lambda p: p.write_text("timestamp,id\n1,2\n"), "not an MCAP file"),
    (lambda p: _mcap(p, ["/camera/image"], library="ros2-bag", metadata=None),
     "foreign MCAP .*library 'ros2-bag'.*'/camera/image'"),
    (lambda p: _mcap(p, ["/can/rx"], library=f"rig-recorder/{RECORDING_FORMAT_VERSION}",
                     metadata={"format_version": str(RECORDING_FORMAT_VERSION)}),
     r"missing channels \['/can/tx', '/rig/signals', '/rig/events'\]"),
    (lambda p: _mcap(p, ["/can/rx"], library="rig-recorder/9",
                     metadata={"format_version": "9"}), "format version 9"),
])
def test_bad_files_get_a_clear_error(work: Path, make: Any, match: str,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    p = work / "bad.mcap"
    make(p)
    with pytest.raises(RecordingError, match=match):
        load_recorded_run(p)
    assert rig_main(["replay", str(p)]) == 2
    assert str(p) in capsys.readouterr().err


def test_truncated_before_the_first_chunk(recording: Path, work: Path) -> None:
    with recording.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    first_chunk = min(c.chunk_start_offset for c in summary.chunk_indexes)
    p = work / "head.mcap"
    p.write_bytes(recording.read_bytes()[: first_chunk + 40])
    with pytest.raises(RecordingError,
                       match=rf"nothing to replay.*truncated at byte {first_chunk} "):
        load_recorded_run(p)


def test_missing_file_and_directory(work: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load_recorded_run(work / "nope.mcap")
    with pytest.raises(IsADirectoryError):
        load_recorded_run(work)


def test_config_replace_keeps_other_sections() -> None:
    """Guard for the comparison tests: weight set 2 is a different controller."""
    cfg2 = CFG.replace(design={"weight_set": 2})
    assert cfg2.design.weight_set == 2 and replace(cfg2.vehicle) == CFG.vehicle


def test_indexed_gather_and_piecewise_decoding_equal_the_record_walk(recording: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The MessageIndex fast path hands out exactly what walking every record does."""
    from rig.recording import scan as scan_mod
    from rig.replay.recorded import RunDecoder, assemble_run

    fast = load_recorded_run(recording)
    # decoded in small pieces (a flush every few chunks, as for long recordings)
    dec = RunDecoder(flush_messages=97)
    scan = scan_mod.scan_recording(recording, dec.handlers(), after_chunk=dec.after_chunk)
    dec.flush(final=True)
    pieces = assemble_run(recording, scan, dec.pieces, dec.first)
    assert len(dec.pieces) > 3
    monkeypatch.setattr(scan_mod._Segment, "_gather", lambda self, buf, index: None)
    slow = load_recorded_run(recording)
    for other in (slow, pieces):
        assert fast.rx == other.rx and fast.tx == other.tx and fast.events == other.events
        for name in ("tick", "t_ns", "lateness_ns", "compute_ns", "spool_cmd", "force_ref_n",
                     "valve_enable"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(other, name))
        assert fast.first_internals == other.first_internals
    assert fast.scan.messages == slow.scan.messages > 5 * fast.tick.size


def test_recorded_timing_round_trips_to_the_nanosecond(recording: Path) -> None:
    """Lateness / compute time come back as the integer ns the loop was given (they
    decide overruns and the heartbeat's p99); reference: the generator's seeded draw."""
    run = load_recorded_run(recording)
    n = run.tick.size
    rng = np.random.default_rng(1)
    late = rng.integers(2_000, 90_000, size=n)
    comp = rng.integers(15_000, 60_000, size=n)
    for k, v in LATE.items():
        late[k] = v
    np.testing.assert_array_equal(run.lateness_ns, late)
    np.testing.assert_array_equal(run.compute_ns, comp)


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(where=st.floats(0.0, 1.0), xor=st.integers(1, 255))
def test_a_flipped_byte_never_yields_wrong_frames(recording: Path, where: float,
                                                  xor: int) -> None:
    """One corrupted byte anywhere: a clear error, or frames that are a prefix of the
    true ones (chunk CRCs; MessageIndex offsets are checked against the records), and
    never a recording called complete (data-section and summary CRCs, closing magic)."""
    data = bytearray(recording.read_bytes())
    full = load_recorded_run(recording)
    i = min(int(where * len(data)), len(data) - 1)
    data[i] ^= xor
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.mcap"
        p.write_bytes(bytes(data))
        try:
            run = load_recorded_run(p)
        except RecordingError:
            return
    assert not run.complete, (i, xor)
    assert run.rx == full.rx[: len(run.rx)] and run.tx == full.tx[: len(run.tx)]
    np.testing.assert_array_equal(run.spool_cmd, full.spool_cmd[: run.tick.size])


def test_reader_process_replay_equals_in_process(recording: Path, work: Path) -> None:
    """Reading in a forked process while replaying (long recordings) changes nothing."""
    a = replay_recording(recording, reader_process=False)
    b = replay_recording(recording, reader_process=True)
    timing = {"elapsed_s": 0, "realtime_factor": 0}
    assert b.bit_exact and a.summary() | timing == b.summary() | timing
    np.testing.assert_array_equal(a.force_ref_n, b.force_ref_n)
    data = recording.read_bytes()
    cut = work / "cut-reader.mcap"
    cut.write_bytes(data[: _inside_a_chunk(recording, 0.5)])
    c = replay_recording(cut, reader_process=True)
    assert not c.complete and c.bit_exact and c.ticks < a.ticks
    foreign = _mcap(work / "foreign-reader.mcap", ["/x"], library="other", metadata=None)
    with pytest.raises(RecordingError, match="foreign MCAP"):
        replay_recording(foreign, reader_process=True)


# ---------------------------------------------------------------------------- bus trouble

#: ticks of the bus-trouble recording (1 s, armed at tick 100; heartbeat every 100 ticks)
EXT_TICK = 150          # an extended-ID frame with SensorData's ID (+ a benign error frame)
BUSERROR_TICK = 200     # error frame, class CAN_ERR_BUSERROR -> BUS_ERROR
RECV_OFF_TICK = 350     # recv raises ENETDOWN at its second call -> BUS_OFF
SEND_TICK = 500         # ValveCommand send raises ENOBUFS (armed) -> BUS_ERROR
BUSOFF_TICK = 700       # error frame CAN_ERR_BUSOFF on a heartbeat tick -> BUS_OFF; the
#                         tick's second FaultReport send fails (the first goes out)
RECV_AGAIN_TICK = 720   # recv raises EAGAIN (BlockingIOError) while latched
FLAKY_COMMANDS: dict[int, tuple[str, Any]] = {
    250: ("reset", None), 300: ("arm", None), 400: ("reset", None), 450: ("arm", None),
    550: ("reset", None), 600: ("arm", None), 760: ("reset", None), 800: ("arm", None)}


class FlakyBus(can.BusABC):
    """The controller's bus with scheduled failures (a test double around the virtual
    bus): ``recv_errors`` {(tick, n-th recv call of the tick): exception},
    ``send_errors`` {(tick, frame id, n-th send of that id in the tick): exception}."""

    def __init__(self, inner: can.BusABC, recv_errors: dict[tuple[int, int], Exception],
                 send_errors: dict[tuple[int, int, int], Exception]) -> None:
        super().__init__(channel="flaky")
        self.inner = inner
        self.recv_errors = dict(recv_errors)
        self.send_errors = dict(send_errors)
        self.tick = -1
        self._recv_calls = 0
        self._sends: dict[int, int] = {}

    def set_tick(self, k: int) -> None:
        self.tick, self._recv_calls = k, 0
        self._sends.clear()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        n, self._recv_calls = self._recv_calls, self._recv_calls + 1
        exc = self.recv_errors.pop((self.tick, n), None)
        if exc is not None:
            raise exc
        return self.inner.recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        raise NotImplementedError

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        n = self._sends.get(msg.arbitration_id, 0)
        self._sends[msg.arbitration_id] = n + 1
        exc = self.send_errors.pop((self.tick, msg.arbitration_id, n), None)
        if exc is not None:
            raise exc
        self.inner.send(msg, timeout)


@pytest.fixture(scope="module")
def flaky_recording(work: Path, design_blob: bytes) -> Path:
    """1 s through the real loop with error frames, an extended-ID frame and recv /
    send exceptions; reset and re-armed after every fault."""
    from rig.bus.core import CAN_ERR_BUSERROR, CAN_ERR_BUSOFF, CAN_ERR_LOSTARB

    flaky: list[FlakyBus] = []

    def wrap(bus: can.BusABC) -> can.BusABC:
        flaky.append(FlakyBus(bus, {
            (RECV_OFF_TICK, 1): can.CanOperationError("Network is down",
                                                      error_code=errno.ENETDOWN),
            (RECV_AGAIN_TICK, 0): OSError(errno.EAGAIN, "Resource temporarily unavailable"),
        }, {
            (SEND_TICK, VALVE_COMMAND_ID, 0): OSError(errno.ENOBUFS,
                                                      "No buffer space available"),
            (BUSOFF_TICK, FAULT_REPORT_ID, 1): can.CanOperationError("Transmit buffer full"),
        }))
        return flaky[0]

    def inject(k: int, rig_bus: can.BusABC) -> None:
        flaky[0].set_tick(k)
        error_class = {BUSERROR_TICK: CAN_ERR_BUSERROR, BUSOFF_TICK: CAN_ERR_BUSOFF,
                       EXT_TICK: CAN_ERR_LOSTARB}.get(k)
        if error_class is not None:
            rig_bus.send(can.Message(arbitration_id=error_class, is_error_frame=True,
                                     is_extended_id=False, data=bytes(8)))
        if k == EXT_TICK:   # not SensorData: a 29-bit frame that happens to share its ID
            rig_bus.send(can.Message(arbitration_id=SENSOR_DATA_ID, is_extended_id=True,
                                     data=bytes(range(8))))

    path = record_emulated_run(work / "flaky.mcap", 1.0, cfg=CFG, design_bytes=design_blob,
                               commands=FLAKY_COMMANDS, wrap_bus=wrap, before_tick=inject)
    flaky[0].shutdown()
    assert not flaky[0].recv_errors and not flaky[0].send_errors   # all happened
    return path


def _fault_events(path: Path) -> list[tuple[int, str]]:
    return [(e.tick, e.detail["fault"]) for e in read_run(path).events if e.kind == "fault"]


def test_bus_trouble_is_recorded(flaky_recording: Path) -> None:
    """The recording holds what replay needs (read_run, checked here against the mcap
    library's reader)."""
    run = read_run(flaky_recording)
    assert items_of_run(run) == reference_items([flaky_recording])
    flagged = [(f.tick, f.arbitration_id, f.is_error_frame, f.is_extended_id)
               for f in run.frames if f.is_rx and (f.is_error_frame or f.is_extended_id)]
    assert flagged == [(EXT_TICK, 0x002, True, False),
                       (EXT_TICK, SENSOR_DATA_ID, False, True),
                       (BUSERROR_TICK, 0x080, True, False), (BUSOFF_TICK, 0x040, True, False)]
    notes = [(e.tick, e.detail["bus_exception"], e.detail["errno"])
             for e in run.events if e.kind == "note" and "bus_exception" in e.detail]
    assert notes == [(RECV_OFF_TICK, "recv", errno.ENETDOWN),
                     (SEND_TICK, "send", errno.ENOBUFS), (BUSOFF_TICK, "send", None),
                     (RECV_AGAIN_TICK, "recv", errno.EAGAIN)]
    assert _fault_events(flaky_recording) == [
        (BUSERROR_TICK, "BUS_ERROR"), (RECV_OFF_TICK, "BUS_OFF"), (SEND_TICK, "BUS_ERROR"),
        (BUSOFF_TICK, "BUS_OFF")]


@pytest.mark.parametrize("reader_process", [False, True])
def test_bus_trouble_replays_bit_for_bit(flaky_recording: Path, work: Path,
                                         reader_process: bool) -> None:
    """Error frames, an extended-ID frame, recv and send exceptions come back in the
    recorded ticks: same fault codes at the same ticks, the same frames sent."""
    out = work / f"flaky-replayed-{reader_process}.mcap"
    res = replay_recording(flaky_recording, out=out, reader_process=reader_process)
    assert res.bit_exact, res.summary()
    assert res.max_abs_command_diff == 0.0 and res.tx_frames_mismatched == 0
    rec_faults = _fault_events(flaky_recording)
    assert list(zip(res.fault_ticks, res.faults, strict=True)) == rec_faults
    assert res.bus_exceptions_recorded == res.bus_exceptions_raised == 4
    # the replay's own recording (same loop, replay bus) against the original
    a, b = read_run(flaky_recording), read_run(out)

    def frames(run: Any, rx: bool) -> list[tuple[Any, ...]]:
        return [(f.tick, f.arbitration_id, f.data, f.is_error_frame, f.is_extended_id)
                for f in run.frames if f.is_rx is rx]

    assert frames(a, False) == frames(b, False) and frames(a, True) == frames(b, True)
    assert _fault_events(out) == rec_faults

    def notes(run: Any) -> list[Any]:
        return [(e.tick, e.detail) for e in run.events if e.kind == "note"]

    assert notes(a) == notes(b)
    assert len([n for n in notes(a) if "bus_exception" in n[1]]) == 4
    fr = [f for f in a.frames if not f.is_rx and f.tick == BUSOFF_TICK
          and f.arbitration_id == FAULT_REPORT_ID]
    assert len(fr) == 1   # the second FaultReport of that tick failed, the first went out


def test_bus_trouble_decodes_the_same_in_pieces(flaky_recording: Path) -> None:
    """Send attempts are numbered across decoding pieces as in one piece."""
    from rig.replay import scan_recording
    from rig.replay.recorded import RunDecoder, assemble_run

    whole = load_recorded_run(flaky_recording)
    dec = RunDecoder(flush_messages=37)
    scan = scan_recording(flaky_recording, dec.handlers(), after_chunk=dec.after_chunk)
    dec.flush(final=True)
    pieces = assemble_run(flaky_recording, scan, dec.pieces, dec.first)
    assert len(dec.pieces) > 5
    assert pieces.bus_faults == whole.bus_faults
    assert [(f.tick, f.where, f.arbitration_id, f.attempt) for f in whole.bus_faults] == [
        (RECV_OFF_TICK, "recv", None, None), (SEND_TICK, "send", VALVE_COMMAND_ID, 0),
        (BUSOFF_TICK, "send", FAULT_REPORT_ID, 1), (RECV_AGAIN_TICK, "recv", None, None)]


def test_send_attempts_straddling_two_pieces() -> None:
    """A tick's frames split over two pieces: the attempt counts carry over."""
    from rig.replay.bus_faults import BusFault, SendAttempts

    fault = BusFault(7, "send", "OSError", "x", None, FAULT_REPORT_ID)
    sa = SendAttempts()
    fr = (7, FAULT_REPORT_ID, b"\x00", 0)
    assert sa.number([(6, FAULT_REPORT_ID, b"", 0), fr], [1, 2], []) == []
    got = sa.number([(7, VALVE_COMMAND_ID, b"", 0), fr], [3, 5], [(4, fault)])
    assert [f.attempt for f in got] == [1]     # after the FaultReport of piece one
    got = sa.number([], [], [(9, fault)])
    assert [f.attempt for f in got] == [3]     # + piece two's failed and sent one


@pytest.mark.parametrize("exc", [
    can.CanOperationError("Network is down", error_code=errno.ENETDOWN),
    can.CanOperationError("Transmit buffer full"),
    OSError(errno.ENOBUFS, "No buffer space available"),
    OSError(errno.ENODEV, "No such device"),
    OSError(errno.EAGAIN, "Resource temporarily unavailable"),
    can.CanTimeoutError("timed out", error_code=errno.ETIMEDOUT),
    can.CanError("odd interface error"),
])
def test_a_recorded_bus_exception_is_rebuilt_alike(exc: Exception) -> None:
    """Recorded as the loop records it, rebuilt by replay: same class, message, errno
    and fault classification."""
    from rig.bus.core import classify_bus_exception, errno_of
    from rig.replay.bus_faults import bus_fault_of
    from rig.service.hardware import bus_exception_note as _bus_exception

    fault = bus_fault_of({"tick": 3, "kind": "note", "detail": json.loads(json.dumps(
        _bus_exception("recv", exc)))})
    assert fault is not None
    again = fault.exception()
    assert type(again) is type(exc) and str(again) == str(exc)
    assert errno_of(again) == errno_of(exc)
    assert classify_bus_exception(again) is classify_bus_exception(exc)


def test_replay_bus_frame_flags() -> None:
    """The recorded flags become the Message's, and only they: a frame recorded without
    flags is a standard data frame (no guessing from the ID: the recording format
    records every extended frame as such)."""
    from rig.replay import ERROR_FRAME, EXTENDED_ID

    bus = McapReplayBus([(0, 1, 0x80, bytes(8), ERROR_FRAME),
                         (0, 2, 0x100, bytes(8), EXTENDED_ID),
                         (0, 3, 0x100, bytes(8), 0),
                         (0, 4, 0x18FF00, bytes(8), EXTENDED_ID),
                         (0, 5, 0x7FF, bytes(8), 0)])
    bus.advance(0)
    got = [(m.arbitration_id, m.is_error_frame, m.is_extended_id)
           for m in iter(lambda: bus.recv(0), None)]
    assert got == [(0x80, True, False), (0x100, False, True), (0x100, False, False),
                   (0x18FF00, False, True), (0x7FF, False, False)]
    bus.shutdown()


@pytest.mark.parametrize("drop", ["flags", "recv", "send", "attempt"])
def test_bus_trouble_needs_every_piece(flaky_recording: Path, drop: str) -> None:
    """Without the frame flags, the recv or send exceptions, or the send attempt
    numbers the replay differs from the recording (what an older replay did)."""
    from dataclasses import replace as dc_replace

    run = load_recorded_run(flaky_recording)
    if drop == "flags":
        run.rx = [(t, ts, fid, d, 0) for t, ts, fid, d, _ in run.rx]
    elif drop == "attempt":   # "the first send of the ID in the tick" instead
        run.bus_faults = [dc_replace(f, attempt=None) for f in run.bus_faults]
    else:
        run.bus_faults = [f for f in run.bus_faults if f.where != drop]
    res = replay_recording(flaky_recording, run=run)
    assert not res.bit_exact and res.tx_frames_mismatched > 0


# ---------------------------------------------------------------------------- segment sets

SEGMENTED_CFG = CFG.replace(recording={"rotate_seconds": 1.0})


def _record_segmented(where: Path, design_blob: bytes, seed: int) -> Path:
    """3.2 s at 1 kHz with rotate_seconds = 1: run.mcap, run.001 ... run.003.mcap."""
    where.mkdir()
    return record_emulated_run(where / "run.mcap", 3.2, cfg=SEGMENTED_CFG,
                               design_bytes=design_blob, seed=seed)


@pytest.fixture(scope="module")
def segmented(work: Path, design_blob: bytes) -> Path:
    return _record_segmented(work / "segmented", design_blob, 5)


@pytest.fixture(scope="module")
def other_segmented(work: Path, design_blob: bytes) -> Path:
    """Another run with the same file names (a foreign file for the first one's slots)."""
    return _record_segmented(work / "other-segmented", design_blob, 6)


@pytest.fixture
def seg_copy(segmented: Path, tmp_path: Path) -> Path:
    d = tmp_path / "copy"
    shutil.copytree(segmented.parent, d)
    return d / "run.mcap"


def _seg(base: Path, k: int) -> Path:
    return base if k == 0 else base.with_name(f"run.{k:03d}.mcap")


def test_segmented_run_replays_whole(segmented: Path) -> None:
    assert sorted(p.name for p in segmented.parent.iterdir()) == [
        "run.001.mcap", "run.002.mcap", "run.003.mcap", "run.mcap"]
    res = replay_recording(segmented)
    assert res.complete and res.bit_exact and res.ticks == 3200, res.summary()
    assert res.notes == []
    run = load_recorded_run(segmented)
    assert run.scan.segments == [_seg(segmented, k) for k in range(4)]


@pytest.mark.parametrize("gone", [1, 2, 3])
def test_a_missing_segment_is_never_complete(seg_copy: Path, gone: int,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    _seg(seg_copy, gone).unlink()
    res = replay_recording(seg_copy)
    run_id = load_recorded_run(seg_copy).metadata["run_id"]
    assert not res.complete and res.ticks == 1000 * gone
    assert res.bit_exact                              # what was read replays exactly
    if gone < 3:                                      # a later segment shows the gap's end
        assert res.stopped_at == (
            f"run.{gone:03d}.mcap (segment {gone} of run {run_id}) missing: ticks "
            f"{1000 * gone}-{1000 * gone + 999} are not in the recording; "
            f"run.{gone + 1:03d}.mcap and later segments were not read")
    else:
        assert res.stopped_at == (
            f"run.003.mcap (segment 3 of run {run_id}) is missing: the run went on after "
            f"tick 2999 (from item {_items_before(seg_copy, 3)}); nothing after segment 2 "
            "was read")
    assert any(res.stopped_at in n for n in res.notes)
    # the same from the report's and the reference reader's side
    assert load_series(seg_copy).scan.stopped_at == res.stopped_at
    run = read_run(seg_copy)
    assert not run.complete and run.stopped_at == res.stopped_at
    assert run.records[-1].tick == 1000 * gone - 1
    assert rig_main(["replay", str(seg_copy)]) == 0
    assert f"INCOMPLETE RECORDING: {res.stopped_at}" in capsys.readouterr().out


def _items_before(base: Path, k: int) -> int:
    """The MCAP sequence segment ``k`` starts at (from the previous segment's end)."""
    with _seg(base, k - 1).open("rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    return int(meta["rig_segment_end"]["sequence_end"])


def test_two_missing_segments_are_named(seg_copy: Path) -> None:
    _seg(seg_copy, 1).unlink()
    _seg(seg_copy, 2).unlink()
    res = replay_recording(seg_copy)
    assert not res.complete and res.ticks == 1000
    assert "run.001.mcap ... run.002.mcap (segments 1-2 of run" in str(res.stopped_at)
    assert "ticks 1000-2999 are not in the recording; run.003.mcap" in str(res.stopped_at)


@pytest.mark.parametrize(("slot", "theirs"), [(1, 1), (2, 0)])
def test_a_foreign_file_in_a_segment_slot_is_refused(seg_copy: Path, other_segmented: Path,
                                                     slot: int, theirs: int) -> None:
    """Another run's file (same names, even the same segment index) is never merged."""
    shutil.copy(_seg(other_segmented, theirs), _seg(seg_copy, slot))
    ours = load_recorded_run(seg_copy).metadata["run_id"]
    other = load_recorded_run(other_segmented).metadata["run_id"]
    assert ours != other
    res = replay_recording(seg_copy)
    assert not res.complete and res.ticks == 1000 * slot
    assert res.stopped_at == (
        f"run.{slot:03d}.mcap is not segment {slot} of run {ours}: it is segment {theirs} "
        f"of run {other} (foreign) -- not merged; reading stopped after segment {slot - 1} "
        f"(last tick {1000 * slot - 1})")
    assert res.bit_exact and res.tx_frames_mismatched == 0     # nothing foreign compared
    run = load_recorded_run(seg_copy)
    assert run.scan.segments == [_seg(seg_copy, k) for k in range(slot)]
    ref = read_run(seg_copy)
    assert ref.stopped_at == res.stopped_at and ref.segments == run.scan.segments
    assert ref.records[-1].tick == 1000 * slot - 1


def test_a_foreign_non_segment_file_is_refused(seg_copy: Path, plain_recording: Path,
                                               work: Path) -> None:
    shutil.copy(_mcap(work / "x.mcap", ["/can/rx"], library="other", metadata=None),
                _seg(seg_copy, 1))
    res = replay_recording(seg_copy)
    assert not res.complete and res.ticks == 1000
    assert "run.001.mcap is not segment 1 of run" in str(res.stopped_at)
    assert "no segment identity (a foreign file) -- not merged" in str(res.stopped_at)


def test_a_later_segment_given_directly_says_where_to_start(
        segmented: Path, capsys: pytest.CaptureFixture[str]) -> None:
    later = _seg(segmented, 1)
    run_id = load_recorded_run(segmented).metadata["run_id"]
    msg = (f"{later}: this is segment 1 of run {run_id}; a run is read from its first "
           f"segment: start from {segmented}")
    with pytest.raises(RecordingError) as exc:
        replay_recording(later)
    assert str(exc.value) == msg
    with pytest.raises(RecordingError):
        replay_recording(later, reader_process=True)
    with pytest.raises(ValueError, match="start from"):
        read_run(later)
    assert len(read_run(later, follow_segments=False).records) == 1000
    assert rig_main(["replay", str(later)]) == 2
    assert rig_main(["report", str(later), "--out", str(later.parent / "r")]) == 2
    err = capsys.readouterr().err
    assert err.count(f"start from {segmented}") == 2


def test_a_stale_file_after_the_last_segment_is_ignored(seg_copy: Path,
                                                        other_segmented: Path) -> None:
    """Re-recording to the same name leaves an older run's later segments behind."""
    shutil.copy(_seg(other_segmented, 1), _seg(seg_copy, 4))
    res = replay_recording(seg_copy)
    assert res.complete and res.bit_exact and res.ticks == 3200
    assert res.notes == [f"run.004.mcap is not part of this recording (run "
                         f"{load_recorded_run(seg_copy).metadata['run_id']} ended with "
                         "segment 3): ignored"]


def test_a_renamed_segment_set_is_still_one_run(seg_copy: Path) -> None:
    """Identity is in the files, not their names: a set renamed as a whole reads whole,
    and a later segment names the renamed first one."""
    for k in range(4):
        _seg(seg_copy, k).rename(_seg(seg_copy, k).with_name(
            "trial-7.mcap" if k == 0 else f"trial-7.{k:03d}.mcap"))
    first = seg_copy.with_name("trial-7.mcap")
    res = replay_recording(first)
    assert res.complete and res.bit_exact and res.ticks == 3200, res.summary()
    with pytest.raises(RecordingError, match=f"start from {first}$"):
        replay_recording(first.with_name("trial-7.002.mcap"))


def test_segment_identity_in_every_file(segmented: Path) -> None:
    """Each segment's 'rig' record: one run id, its index, where its items start; its
    end record: the next file or final, where its items end, its ticks."""
    heads, ends = [], []
    for k in range(4):
        with _seg(segmented, k).open("rb") as f:
            meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        heads.append(meta["rig"])
        ends.append(meta["rig_segment_end"])
    assert len({h["run_id"] for h in heads} | {e["run_id"] for e in ends}) == 1
    assert [h["segment"] for h in heads] == ["0", "1", "2", "3"]
    assert [h["first_segment"] for h in heads] == ["run.mcap"] * 4
    assert [e["next_segment"] for e in ends] == ["run.001.mcap", "run.002.mcap",
                                                 "run.003.mcap", ""]
    assert [e["final"] for e in ends] == ["false", "false", "false", "true"]
    assert heads[0]["sequence_start"] == "0"
    for k in range(1, 4):
        assert heads[k]["sequence_start"] == ends[k - 1]["sequence_end"]
        assert heads[k]["first_tick"] == ends[k]["first_tick"] == str(1000 * k)
    # the shutdown's events come at tick 3200, after the last tick record (3199)
    assert [e["last_tick"] for e in ends] == ["999", "1999", "2999", "3200"]


# ---------------------------------------------------------------------------- file ends


def _summary_start(path: Path) -> int:
    data = path.read_bytes()
    (start,) = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)
    return int(start)


@pytest.mark.parametrize("damage", ["cut_magic", "cut_footer", "flip_summary",
                                    "flip_footer", "flip_magic"])
def test_a_damaged_file_end_is_noticed_and_the_chunks_still_read(
        recording: Path, work: Path, damage: str) -> None:
    data = bytearray(recording.read_bytes())
    summary = _summary_start(recording)
    if damage == "cut_magic":
        data = data[:-8]
    elif damage == "cut_footer":
        data = data[:-20]
    elif damage == "flip_summary":
        data[(summary + len(data) - 37) // 2] ^= 0x10
    elif damage == "flip_footer":
        data[len(data) - 8 - 29 + 12] ^= 0x01
    else:
        data[-3] ^= 0x40
    p = work / f"end-{damage}.mcap"
    p.write_bytes(bytes(data))
    full = load_recorded_run(recording)
    run = load_recorded_run(p)
    assert not run.complete
    expected = {"cut_magic": "closing magic missing or damaged",
                "cut_footer": "closing magic missing or damaged",
                "flip_summary": "summary section or Footer damaged (CRC mismatch",
                "flip_footer": "Footer points at a summary section",
                "flip_magic": "closing magic missing or damaged"}[damage]
    assert str(run.stopped_at).startswith(f"{p}: {expected}"), run.stopped_at
    assert "every chunk before it was read" in str(run.stopped_at)
    np.testing.assert_array_equal(run.tick, full.tick)     # all the data is there
    assert run.tx == full.tx and run.rx == full.rx and run.events == full.events
    res = replay_recording(p, run=run)
    assert res.bit_exact and res.ticks == full.tick.size and not res.complete
    ref = read_run(p)                                      # the Python API agrees
    assert not ref.complete and expected in str(ref.stopped_at)
    assert len(ref.records) == full.tick.size


def test_a_damaged_data_section_record_is_noticed(recording: Path, work: Path) -> None:
    """The 'rig' metadata record has no CRC of its own: the data-section CRC in DataEnd
    covers it."""
    data = bytearray(recording.read_bytes())
    i = data.index(b"clock_offset_ns")
    data[i] ^= 0x01                           # a metadata key, outside every chunk
    p = work / "meta-flip.mcap"
    p.write_bytes(bytes(data))
    run = load_recorded_run(p)
    assert not run.complete and "data section damaged (CRC mismatch" in str(run.stopped_at)
    assert not read_run(p).complete


@pytest.mark.parametrize("command", ["replay", "report"])
def test_non_regular_input_is_refused_without_reading(command: str, tmp_path: Path) -> None:
    """/dev/zero and a pipe whose writer never closes: refused as not a regular file
    before a byte is read (reading them would never end; controller.files), a large
    regular non-MCAP file on its first 8 bytes."""
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    big = tmp_path / "big.mcap"
    with big.open("wb") as f:
        f.write(b"timestamp,can_id,data\n")
        f.truncate(1 << 30)                   # sparse
    for src, frag in (("/dev/zero", "is a character device, expected a regular file"),
                      (str(fifo), "is a FIFO (named pipe), expected a regular file"),
                      (str(big), "not an MCAP file (first bytes")):
        proc = subprocess.run([sys.executable, "-m", "rig.cli", command, src],
                              capture_output=True, text=True, timeout=60,
                              cwd=Path(__file__).resolve().parents[1])
        assert proc.returncode == 2, proc.stderr
        assert f"{src}: {frag}" in proc.stderr
        assert "Traceback" not in proc.stderr


# ---------------------------------------------------------------------------- loop settings


@given(blending=st.integers(0, 3), weight_set=st.integers(1, 3),
       warmup=st.none() | st.integers(0, 10_000), single=st.none() | st.integers(0, 20),
       excite=st.booleans())
def test_loop_settings_round_trip_through_the_metadata(blending: int, weight_set: int,
                                                       warmup: int | None, single: int | None,
                                                       excite: bool) -> None:
    """What the service writes (JSON per key, as the recorder stores it) reads back equal."""
    s = LoopSettings(blending, weight_set, warmup, single, excite)
    stored = {k: json.dumps(v) for k, v in s.metadata().items()}
    assert LoopSettings.from_metadata(stored) == s


@pytest.mark.parametrize("key, value, match", [
    ("weight_set", None, "no loop setting 'weight_set'"),
    ("blending", "fuzzy", "'blending' is not JSON"),
    ("blending", '"fuzzy"', "'blending' = 'fuzzy': expected int"),
    ("excitation", "1", "'excitation' = 1: expected bool"),
    ("warmup_ticks", "true", "'warmup_ticks' = True: expected int or null"),
])
def test_a_recording_without_valid_loop_settings_is_refused(plain_recording: Path, key: str,
                                                            value: str | None,
                                                            match: str) -> None:
    """No guessing the mode or weight set from tick records or the configuration: a
    recording of this format always has its loop settings, one that lacks one is refused
    naming the key."""
    run = load_recorded_run(plain_recording)
    meta = run.scan.rig_metadata
    if value is None:
        del meta[key]
    else:
        meta[key] = value
    with pytest.raises(RecordingError, match=f"{plain_recording.name}: .*{match}"):
        replay_recording(plain_recording, run=run)
