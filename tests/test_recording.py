"""MCAP recording: round trip, schemas, attachments, rotation, SIGKILL survival, drops."""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from controller.config import RecordingConfig, config_hash, config_to_toml, default_config
from rig.recording.recorder import CanFrameRecord, EventRecord, RunRecorder, read_run, segment_paths
from rig.recording.scan import RecordingError, scan_recording
from rig.recording.schema import (
    NONFINITE_NUMBER,
    RECORDING_FORMAT_VERSION,
    SIGNAL_KEYS,
    TIMING_KEYS,
    TOPIC_INTERNALS,
    TOPIC_LOG,
    TOPIC_SCENE,
    TOPIC_SIGNALS,
    TOPIC_TF,
    TOPICS,
)
from tests.support.mcap_reference import items_of_run, reference_items
from tests.support.processes import stop_and_wait_stopped

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(120)
CFG = default_config()
TOML = config_to_toml(CFG)


def rcfg(**kw: Any) -> RecordingConfig:
    return replace(CFG.recording, **kw)


def recorder(path: Path, **kw: Any) -> RunRecorder:
    opts = {k: kw.pop(k) for k in ("poll_s", "compression", "max_chunk_age_s", "pipe_bytes",
                                   "tick_layout", "blocking") if k in kw}
    kw.setdefault("batch_ticks", 1)    # one tick per write: the drop tests count single ticks
    return RunRecorder(path, rcfg(**kw), config_toml=TOML, design_bytes=b"\x93NUMPY-design",
                       metadata={"operator": "test", "seed": 7}, **{"poll_s": 0.001, **opts})


def tick_record(k: int) -> dict[str, Any]:
    return {"tick": k, "rattlespace_m": 1e-3 * math.sin(k), "force_meas_n": 10.0 * k,
            "lifecycle": "ACTIVE", "fault": "", "valve_enable": 1,
            "q": np.array([0.1 * k, 2.0, 3.5]), "firing_weight": [1.0, 0.0, 0.0],
            "active": [True, True, False], "flags": 0,
            "x_post": np.arange(12.0).reshape(3, 4) * k,
            "wake_late_s": 2e-5, "overrun": False}


def expected_json(record: dict[str, Any]) -> dict[str, Any]:
    """What a record reads back as: arrays as lists, matrices flat row-major (independent
    of the writer)."""
    return {k: (v.ravel().tolist() if isinstance(v, np.ndarray) else v)
            for k, v in record.items()}


# ----------------------------------------------------------------------- round trip


def write_mixed(rec: RunRecorder, n: int) -> list[tuple[str, Any]]:
    """Write a loop-like sequence; return the expected timeline."""
    expected: list[tuple[str, Any]] = []
    for k in range(n):
        t = 1_000_000_000 + k * 1_000_000
        rx = bytes([(k + i) & 0xFF for i in range(8)])
        assert rec.can_frame(t, k, 0x100, bytearray(rx), True)
        expected.append(("frame", (t, k, 0x100, rx, True)))
        if k % 10 == 0:
            assert rec.can_frame(t + 1, k, 0x200, rx[:5], True)
            expected.append(("frame", (t + 1, k, 0x200, rx[:5], True)))
        r = tick_record(k)
        assert rec.tick(t + 2, r)
        expected.append(("record", (t + 2, k, expected_json(r))))
        assert rec.can_frame(t + 3, k, 0x080, rx[::-1], False)
        expected.append(("frame", (t + 3, k, 0x080, rx[::-1], False)))
        if k in (5, 50, 51):
            detail = {"name": "arm", "args": {}, "source": "zenoh"} if k == 5 else \
                {"from": "ACTIVE", "to": "FAULT", "reason": "STALE_SENSOR"}
            kind = "command" if k == 5 else "lifecycle"
            assert rec.event(t + 4, k, kind, detail)
            expected.append(("event", (t + 4, k, kind, detail)))
    return expected


def timeline_of(path: Path) -> list[tuple[str, Any]]:
    run = read_run(path)
    out: list[tuple[str, Any]] = []
    for item in run.timeline():
        if isinstance(item, CanFrameRecord):
            out.append(("frame", (item.t_ns, item.tick, item.arbitration_id, item.data,
                                  item.is_rx)))
        elif isinstance(item, EventRecord):
            out.append(("event", (item.t_ns, item.tick, item.kind, item.detail)))
        else:
            out.append(("record", (item.t_ns, item.tick, item.data)))
    return out


def test_round_trip_in_order(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with recorder(path) as rec:
        expected = write_mixed(rec, 300)
    assert rec.dropped == 0 and rec.malformed == 0 and rec.error is None
    assert rec.written == len(expected)
    run = read_run(path)
    assert run.complete and run.stopped_at is None
    assert timeline_of(path) == expected


frame_st = st.tuples(st.integers(0, 0x7FF), st.binary(min_size=0, max_size=8), st.booleans())
value_st = st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.integers(-2**53, 2**53),
                     st.booleans(), st.none(), st.text(max_size=6),
                     st.lists(st.floats(allow_nan=False, allow_infinity=False), max_size=4))


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.lists(frame_st, max_size=40),
       records=st.lists(st.dictionaries(st.sampled_from(
           sorted(SIGNAL_KEYS | TIMING_KEYS | {"q", "u_model", "custom"})), value_st,
           max_size=6), max_size=10))
def test_round_trip_property(tmp_path: Path, frames: list[tuple[int, bytes, bool]],
                             records: list[dict[str, Any]]) -> None:
    path = tmp_path / f"p{time.monotonic_ns()}.mcap"
    expected: list[tuple[str, Any]] = []
    with recorder(path) as rec:
        for i, (arb, data, is_rx) in enumerate(frames):
            rec.can_frame(i * 7, i, arb, data, is_rx)
            expected.append(("frame", (i * 7, i, arb, data, is_rx)))
            if i < len(records):
                r = {**records[i], "tick": i}
                rec.tick(i * 7 + 1, r)
                expected.append(("record", (i * 7 + 1, i, r)))
    assert timeline_of(path) == expected


def test_nonfinite_values_become_the_sentinel_and_are_listed(tmp_path: Path) -> None:
    path = tmp_path / "nan.mcap"
    with recorder(path) as rec:
        rec.tick(0, {"tick": 0, "force_ref_n": float("nan"), "q": np.array([1.0, np.inf]),
                     "wake_late_s": 1e-5})
    (r,) = read_run(path).records
    assert r.data["force_ref_n"] is None and r.data["q"] == [1.0, None]
    assert sorted(r.data["nonfinite"]) == ["force_ref_n", "q"]
    with path.open("rb") as f:     # on the wire: the documented number (JSON has no NaN)
        raw = {ch.topic: json.loads(m.data) for _, ch, m in make_reader(f).iter_messages(
            topics=[TOPIC_SIGNALS, TOPIC_INTERNALS])}
    assert raw[TOPIC_SIGNALS]["force_ref_n"] == NONFINITE_NUMBER == -1e308
    assert raw[TOPIC_INTERNALS]["q"] == [1.0, NONFINITE_NUMBER]


# ----------------------------------------------------------------------- schemas, attachments


_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}


def conforms(value: Any, schema: dict[str, Any]) -> bool:
    """Independent checker for the JSON-schema keywords the recording uses."""
    types = schema.get("type")
    if types is not None:
        names = [types] if isinstance(types, str) else types

        def is_type(v: Any, n: str) -> bool:
            if n == "integer":
                return isinstance(v, int) and not isinstance(v, bool)
            if n == "number":
                return isinstance(v, int | float) and not isinstance(v, bool)
            return isinstance(v, _TYPES[n])

        if not any(is_type(value, n) for n in names):
            return False
    if "enum" in schema and value not in schema["enum"]:
        return False
    if isinstance(value, int | float) and not isinstance(value, bool):
        if "minimum" in schema and value < schema["minimum"]:
            return False
        if "maximum" in schema and value > schema["maximum"]:
            return False
    if isinstance(value, str) and "pattern" in schema and not re.search(schema["pattern"], value):
        return False
    if isinstance(value, list) and "items" in schema:
        return all(conforms(v, schema["items"]) for v in value)
    if isinstance(value, dict):
        props = schema.get("properties", {})
        if any(k not in value for k in schema.get("required", [])):
            return False
        for k, v in value.items():
            if k in props:
                if not conforms(v, props[k]):
                    return False
            elif schema.get("additionalProperties", True) is False:
                return False
    return True


def strict_json(data: bytes) -> Any:
    def bad(c: str) -> Any:
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(data, parse_constant=bad)


def test_the_writer_process_runs_this_copy_of_the_package(tmp_path: Path) -> None:
    """The writer process (``-m rig.recording.writer``) starts in the directory that
    holds this very ``rig`` package, so it writes this copy's schemas even where
    another copy is installed (an editable install of another checkout, a worktree)."""
    import rig

    with recorder(tmp_path / "run.mcap") as rec:
        assert rec._proc is not None
        cwd = Path(os.readlink(f"/proc/{rec._proc.pid}/cwd"))
    assert (cwd / "rig" / "recording" / "writer.py").is_file()
    assert cwd == Path(rig.__file__).resolve().parents[1]


def test_schemas_messages_attachments_metadata(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with recorder(path) as rec:
        write_mixed(rec, 120)
        rec.tick(0, {"tick": 999, "spool_cmd": float("nan")})
        rec.event(0, 1, "weird-kind", [1, 2])  # type: ignore[arg-type]  # -> "note"
    n_msgs = 0
    with open(path, "rb") as f:                       # mcap's own indexed reader
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic for c in summary.channels.values()}
        assert topics == set(TOPICS)
        for schema, channel, message in reader.iter_messages():
            assert schema is not None
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            sch = json.loads(schema.data)
            assert sch == TOPICS[channel.topic]
            assert sch["$schema"].startswith("https://json-schema.org/")
            msg = strict_json(message.data)
            assert conforms(msg, sch), (channel.topic, msg)
            n_msgs += 1
        atts = {a.name: a.data for a in reader.iter_attachments()}
        assert atts["config.toml"].decode() == TOML
        assert atts["design.npz"] == b"\x93NUMPY-design"
        (meta,) = [m for m in reader.iter_metadata() if m.name == "rig"]
    assert n_msgs > 120 * 3
    assert meta.metadata["config_hash"] == config_hash(CFG)
    assert meta.metadata["operator"] == "test" and meta.metadata["seed"] == "7"
    versions = json.loads(meta.metadata["versions"])
    assert {"python", "numpy", "mcap", "eclipse-zenoh", "lqg-fuzzy-rig"} <= set(versions)
    run = read_run(path)
    assert run.metadata["rig"]["format_version"] == str(RECORDING_FORMAT_VERSION) == "4"
    assert run.events[-1].kind == "note"
    assert run.events[-1].detail == {"kind": "weird-kind", "detail": [1, 2]}


def test_checker_rejects_bad_messages() -> None:
    """The schema checker above is not vacuous."""
    frame = TOPICS["/can/rx"]
    good = {"tick": 1, "t_ns": 5, "id": 256, "data": "0a0b", "dlc": 2}
    assert conforms(good, frame)
    assert not conforms({**good, "data": "0A0"}, frame)
    assert not conforms({**good, "extra": 1}, frame)
    assert not conforms({k: v for k, v in good.items() if k != "dlc"}, frame)
    assert not conforms({**good, "tick": -1}, frame)
    assert not conforms({**good, "tick": True}, frame)


# ----------------------------------------------------------------------- rotation


def test_rotation_by_size_keeps_every_item(tmp_path: Path) -> None:
    path = tmp_path / "rot.mcap"
    with recorder(path, rotate_bytes=16 * 1024, chunk_bytes=4096) as rec:
        expected = write_mixed(rec, 600)
    segs = segment_paths(path)
    assert segs == rec.paths and len(segs) >= 3
    assert [p.name for p in segs[:3]] == ["rot.mcap", "rot.001.mcap", "rot.002.mcap"]
    for p in segs:
        # footers present, each segment self-contained (attachments and metadata repeated)
        with open(p, "rb") as f:
            r = make_reader(f)
            assert {a.name for a in r.iter_attachments()} == {"config.toml", "design.npz"}
        assert p.stat().st_size < 16 * 1024 + 8 * 4096
    run = read_run(path)
    assert run.complete and run.segments == segs
    assert timeline_of(path) == expected
    assert len(read_run(path, follow_segments=False).frames) < len(run.frames)


def _rotated_run(tmp_path: Path) -> tuple[Path, list[Path]]:
    """3.5 s of loop time at 10 Hz recorded in 1 s segments: the path and the segments."""
    path = tmp_path / "t.mcap"
    with recorder(path, rotate_seconds=1.0) as rec:
        for k in range(35):
            rec.can_frame(k * 100_000_000, k, 0x100, b"\x00" * 8, True)
    return path, segment_paths(path)


def test_rotation_by_time(tmp_path: Path) -> None:
    _path, segs = _rotated_run(tmp_path)
    assert len(segs) == 4
    per_seg = [len(read_run(p, follow_segments=False).frames) for p in segs]
    assert per_seg == [10, 10, 10, 5]


def test_segments_carry_run_identity_and_read_run_checks_it(tmp_path: Path) -> None:
    path, segs = _rotated_run(tmp_path)
    run = read_run(path)
    assert run.complete and run.segments == segs and len(run.frames) == 35
    run_id = run.metadata["rig"]["run_id"]
    assert len(run_id) == 32 and run.metadata["rig"]["run_name"] == "t"
    assert run.metadata["rig_segment_end"]["next_segment"] == "t.001.mcap"
    # a second run under the same name: its files are foreign to the first one
    other = tmp_path / "other" / "t.mcap"
    with recorder(other, rotate_seconds=1.0) as rec:
        for k in range(15):
            rec.can_frame(k * 100_000_000, k, 0x100, b"\x01" * 8, True)
    segs[2].write_bytes(segment_paths(other)[1].read_bytes())
    run = read_run(path)
    assert not run.complete and len(run.frames) == 20 and run.segments == segs[:2]
    assert run.stopped_at is not None and run.stopped_at.startswith(
        f"t.002.mcap is not segment 2 of run {run_id}: it is segment 1 of run ")
    segs[2].unlink()
    run = read_run(path)
    assert not run.complete and len(run.frames) == 20
    assert run.stopped_at == (f"t.002.mcap (segment 2 of run {run_id}) missing: ticks 20-29 "
                              "are not in the recording; t.003.mcap and later segments "
                              "were not read")
    with pytest.raises(ValueError, match=f"this is segment 3 of run {run_id}; a run is read "
                                         f"from its first segment: start from {path}"):
        read_run(segs[3])


# ----------------------------------------------------------------------- the reference


def test_read_run_equals_the_mcap_library_reader(tmp_path: Path) -> None:
    """read_run (on the production scanner) against an independent reader (the mcap
    library's indexed reader + json + the channels' JSON schemas), over a rotated run
    with every kind of item: frames (error and extended ones too), tick records of
    three messages, non-finite values, events."""
    path = tmp_path / "ref.mcap"
    with recorder(path, rotate_bytes=16 * 1024, chunk_bytes=4096) as rec:
        write_mixed(rec, 300)
        rec.can_frame(1, 300, 0x1ABCDEF, b"\x05\x06", True, extended_id=True)
        rec.can_frame(2, 300, 0, b"", True, error_frame=True)
        rec.tick(3, {**tick_record(300), "force_ref_n": float("nan"),
                     "q": np.array([np.inf, 1.0, 2.0])})
        rec.event(4, 300, "fault", {"fault": "STALE_SENSOR", "to": "FAULT"})
    segs = segment_paths(path)
    assert len(segs) >= 3
    ref = reference_items(segs)
    run = read_run(path)
    assert run.complete and items_of_run(run) == ref
    assert len(ref) == rec.written
    kinds = {item[0] for item in ref}
    assert kinds == {"frame", "record", "event"}
    assert ref[-3][6] and ref[-4][7]               # the error and the extended frame
    assert sorted(ref[-2][3]["nonfinite"]) == ["force_ref_n", "q"]
    # the index is the rank in recording order
    assert [r.index for r in run.timeline()] == list(range(len(ref)))


@settings(max_examples=60, deadline=None)
@given(start=st.one_of(st.integers((1 << 32) - 600, 1 << 32),        # across the wrap
                      st.integers((2 << 32) - 600, 2 << 32), st.integers(0, 3 << 32)),
       steps=st.lists(st.integers(0, 3), min_size=1,
                                                     max_size=300),
       cuts=st.lists(st.integers(0, 300), max_size=8))
def test_item_numbers_continue_across_the_u32_sequence_wrap(start: int, steps: list[int],
                                                           cuts: list[int]) -> None:
    """MCAP sequence numbers are u32 (the writer's item counter mod 2**32): read_run's
    item numbers keep counting across the wrap, batch after batch."""
    from rig.recording.run_data import _Sequences

    true = start + np.cumsum(np.array(steps, dtype=np.int64))
    seqs = (true % (1 << 32)).astype(np.uint32)
    bounds = [0, *sorted(c for c in cuts if c < true.size), true.size]
    unwrap = _Sequences().unwrap
    got = np.concatenate([unwrap(seqs[a:b]) for a, b in itertools.pairwise(bounds)])
    np.testing.assert_array_equal(got - got[0], true - true[0])
    assert got[0] == true[0] % (1 << 32)


def test_a_torn_record_is_dropped_whole(tmp_path: Path) -> None:
    """A file cut between two chunks may end inside a tick record (one or two of its
    three messages in one chunk, the rest in the next): that record is dropped whole
    and stopped_at says so; every record read is whole."""
    path = tmp_path / "torn.mcap"
    with recorder(path, chunk_bytes=600, compression="none") as rec:
        expected = write_mixed(rec, 40)
    want = {v[1]: v[2] for kind, v in expected if kind == "record"}
    blob = path.read_bytes()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    torn = 0
    for ci in summary.chunk_indexes:
        cut = ci.chunk_start_offset + ci.chunk_length + ci.message_index_length
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(blob[:cut])
        run = read_run(p)
        assert not run.complete and run.stopped_at is not None
        assert all(r.data == {k: v for k, v in want[r.tick].items() if k != "t_ns"}
                   for r in run.records), cut
        m = re.search(r"; dropped torn record of tick (\d+) \([12]/3 parts\)$", run.stopped_at)
        if m:
            torn += 1
            assert int(m.group(1)) == run.records[-1].tick + 1
    assert torn >= 3


def test_the_scanner_holds_a_chunk_not_the_file(tmp_path: Path) -> None:
    """scan_recording reads a file record by record: what it allocates at most while
    scanning a recording of many small chunks is far below the file's size (it read
    each segment whole before: twice the file at the peak)."""
    import tracemalloc

    path = tmp_path / "long.mcap"
    with recorder(path, chunk_bytes=4096, blocking=True) as rec:
        write_mixed(rec, 3000)
    size = path.stat().st_size
    tracemalloc.start()
    try:
        res = scan_recording(path, {TOPIC_SIGNALS: lambda payloads, seqs: None})
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert res.complete and res.messages > 9000
    assert size > 200_000 and peak < size / 4, (size, peak)


def test_another_format_version_is_refused_before_anything_is_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recording of another format version is refused in one line naming both
    versions -- by read_run, the scanner (no handler is ever called), replay and report."""
    from rig.cli import main as rig_main

    path = tmp_path / "v3.mcap"     # format 3: the schemas Foxglove could not convert
    with RunRecorder(path, rcfg(), config_toml=TOML, design_bytes=None,
                     metadata={"format_version": "3"}, poll_s=0.001) as rec:
        write_mixed(rec, 20)
    with open(path, "rb") as f:
        (meta,) = [m for m in make_reader(f).iter_metadata() if m.name == "rig"]
    assert meta.metadata["format_version"] == "3"
    msg = f"{path}: recording format version 3, this software reads version 4 only"
    with pytest.raises(RecordingError) as exc:
        read_run(path)
    assert str(exc.value) == msg

    def never(joined: bytes, seqs: Any) -> None:
        raise AssertionError("a handler was called before the version was checked")

    with pytest.raises(RecordingError, match=re.escape(msg)):
        scan_recording(path, {t: never for t in TOPICS})
    with pytest.raises(RecordingError, match=re.escape(msg)):
        read_run(path, follow_segments=False)
    assert rig_main(["replay", str(path)]) == 2
    assert rig_main(["report", str(path), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.endswith(msg) for line in err)


def hand_made(path: Path, meta: dict[str, str], payloads: list[bytes]) -> Path:
    """A one-channel (/can/rx) file with the writer's header and a 'rig' record."""
    from mcap.writer import Writer

    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library=f"rig-recorder/{RECORDING_FORMAT_VERSION}")
        w.add_metadata("rig", {"format_version": str(RECORDING_FORMAT_VERSION), **meta})
        sid = w.register_schema("rig.CanFrame", "jsonschema", b"{}")
        ch = w.register_channel("/can/rx", "json", sid)
        for k, payload in enumerate(payloads):
            w.add_message(ch, k, payload, k, sequence=k)
        w.finish()
    return path


_IDENTITY = {"run_id": "ab" * 16, "segment": "0", "sequence_start": "0"}
_FRAME = b'{"tick":0,"t_ns":0,"id":1,"data":"","dlc":0}'


def test_a_payload_that_is_not_the_formats_json_is_refused(tmp_path: Path) -> None:
    """Not a torn tail (the chunk passed its CRC): a message that is not one JSON
    object is refused in one line naming the channel, not read as an empty run."""
    path = hand_made(tmp_path / "bad-json.mcap", _IDENTITY,
                     [_FRAME, b'{"tick":1,"t_ns":1,"id":1,"data":"", "dlc"'])
    with pytest.raises(RecordingError, match=rf"^{re.escape(str(path))}: malformed /can/rx "
                                             r"payload \(JSONDecodeError: "):
        read_run(path)
    assert [f.tick for f in read_run(hand_made(tmp_path / "good.mcap", _IDENTITY,
                                               [_FRAME])).frames] == [0]


def test_a_recording_without_segment_identity_is_refused(tmp_path: Path) -> None:
    """Every recording of this format version names its run and segment; a file whose
    'rig' record does not is not read as a run of one segment."""
    path = hand_made(tmp_path / "anon.mcap", {}, [_FRAME])
    with pytest.raises(RecordingError, match=r"'rig' metadata record has no segment "
                                             r"identity \(run_id, segment, sequence_start\)"):
        read_run(path)


# ----------------------------------------------------------------------- SIGKILL


CHILD = """
import sys, time
from dataclasses import replace
from controller.config import default_config, config_to_toml
from rig.recording.recorder import RunRecorder
cfg = default_config()
rec = RunRecorder(sys.argv[1], replace(cfg.recording, chunk_bytes=4096),
                  config_toml=config_to_toml(cfg), design_bytes=None, metadata={})
print(rec.pid, flush=True)
k = 0
while True:
    rec.can_frame(k * 1_000_000, k, 0x100, k.to_bytes(8, "little"), True)
    rec.tick(k * 1_000_000, {"tick": k, "rattlespace_m": k * 1e-6})
    k += 1
    if k % 5 == 0:
        time.sleep(0.001)
"""


def start_recording_child(path: Path) -> tuple[subprocess.Popen[str], int]:
    """A process recording as fast as it can; returns it and its writer process's PID
    once the file has grown past 60 kB."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    writer_pid = int(proc.stdout.readline() or "0")
    assert writer_pid > 0, proc.stderr.read() if proc.stderr else ""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if path.exists() and path.stat().st_size > 60_000:
            break
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        time.sleep(0.05)
    return proc, writer_pid


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"


def raw_complete_chunk_messages(path: Path) -> int:
    """Count messages inside the *complete* chunk records, parsing the MCAP byte layout
    directly (spec: opcode u8, length u64; Chunk = start u64, end u64, size u64, crc u32,
    compression str, records bytes).  Only the channels ``read_run`` reads: the derived
    views (/rig/log, /rig/scene, /tf) are not counted."""
    derived = {TOPIC_LOG.encode(), TOPIC_SCENE.encode(), TOPIC_TF.encode()}
    topics: dict[int, bytes] = {}
    data = path.read_bytes()
    assert data[:8] == b"\x89MCAP0\r\n"
    pos, n = 8, 0
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        body_at, end = pos + 9, pos + 9 + length
        if end > len(data):
            break                              # the torn tail
        if op == 0x06:
            _, _, usize, _ = struct.unpack_from("<QQQI", data, body_at)
            off = body_at + 28
            (clen,) = struct.unpack_from("<I", data, off)
            comp = data[off + 4:off + 4 + clen].decode()
            off += 4 + clen
            (rlen,) = struct.unpack_from("<Q", data, off)
            blob = data[off + 8:off + 8 + rlen]
            recs = zstandard.ZstdDecompressor().decompress(blob, max_output_size=usize) \
                if comp == "zstd" else blob
            p = 0
            while p < len(recs):
                rop, rl = struct.unpack_from("<BQ", recs, p)
                if rop == 0x04:
                    cid, _, tlen = struct.unpack_from("<HHI", recs, p + 9)
                    topics[cid] = recs[p + 17:p + 17 + tlen]
                elif rop == 0x05:
                    (cid,) = struct.unpack_from("<H", recs, p + 9)
                    n += topics.get(cid) not in derived
                p += 9 + rl
        pos = end
    return n


@pytest.mark.skipif(sys.platform != "linux", reason="SIGKILL semantics")
def test_sigkill_of_service_and_writer_leaves_readable_completed_chunks(tmp_path: Path
                                                                        ) -> None:
    """systemd's final SIGKILL hits every process of the unit: the file has no footer,
    yet every message of its complete chunks reads back, as a contiguous prefix."""
    path = tmp_path / "killed.mcap"
    proc, writer_pid = start_recording_child(path)
    try:
        os.kill(writer_pid, signal.SIGKILL)     # started by our child, for this test
    finally:
        os.kill(proc.pid, signal.SIGKILL)       # our own child, by PID
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    run = read_run(path)
    assert not run.complete and run.stopped_at is not None
    n_raw = raw_complete_chunk_messages(path)
    frames, records = run.frames, run.records
    assert len(frames) + len(records) == n_raw > 100
    # a contiguous prefix, nothing corrupted
    assert [f.tick for f in frames] == list(range(len(frames)))
    assert all(f.data == f.tick.to_bytes(8, "little") for f in frames)
    assert [r.tick for r in records] == list(range(len(records)))
    assert run.attachments["config.toml"].decode() == TOML


@pytest.mark.skipif(sys.platform != "linux", reason="SIGKILL semantics")
def test_sigkill_of_the_loop_process_loses_nothing_it_sent(tmp_path: Path) -> None:
    """The writer outlives a killed loop process: it writes everything it was sent and
    finishes the file with its footer."""
    path = tmp_path / "killed.mcap"
    proc, writer_pid = start_recording_child(path)
    os.kill(proc.pid, signal.SIGKILL)           # our own child, by PID
    proc.wait()
    deadline = time.monotonic() + 30
    while pid_alive(writer_pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not pid_alive(writer_pid)
    run = read_run(path)
    assert run.complete and run.stopped_at is None
    frames, records = run.frames, run.records
    assert len(frames) > 500
    assert [f.tick for f in frames] == list(range(len(frames)))
    # the last batch (one frame + one record per tick) is whole
    assert [r.tick for r in records] == list(range(len(frames)))
    assert "ended without closing" in (proc.stderr.read() if proc.stderr else "")


# ----------------------------------------------------------------------- never blocks


def test_writer_behind_drops_whole_batches_keeps_events_and_counts(tmp_path: Path) -> None:
    path = tmp_path / "drop.mcap"
    rec = recorder(path, queue_size=16, pipe_bytes=4096)
    stop_and_wait_stopped(rec.pid)        # the writer (started by this test) stops reading
    accepted = []
    try:
        for k in range(400):
            rec.can_frame(k, k, 0x100, b"\x01", True)
            accepted.append(rec.tick(k, {"tick": k}))
            if k == 300:
                rec.event(k, k, "fault", {"code": 3})   # dropped with its batch: kept back
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    n_ok = sum(accepted)
    assert accepted == [True] * n_ok + [False] * (400 - n_ok) and 10 < n_ok < 200
    assert rec.dropped == 2 * (400 - n_ok)      # frame + record per lost tick, not the event
    rec.close()
    assert rec.error is None
    assert not rec.can_frame(0, 0, 1, b"", True) and rec.dropped == 2 * (400 - n_ok) + 1
    run = read_run(path)
    assert [f.tick for f in run.frames] == list(range(n_ok))
    assert [r.tick for r in run.records] == list(range(n_ok))
    assert [(e.tick, e.detail) for e in run.events] == [(300, {"code": 3})]


def test_batches_of_the_configured_ticks_are_kept_or_dropped_whole(tmp_path: Path) -> None:
    """``[recording] batch_ticks`` ticks go to the writer in one write: with the writer
    stopped, what reaches the file is a whole number of batches, and every item of a
    dropped batch is counted."""
    path = tmp_path / "batch.mcap"
    rec = recorder(path, queue_size=16, pipe_bytes=4096, batch_ticks=8)
    assert rec.batch_ticks == 8
    stop_and_wait_stopped(rec.pid)        # the writer (started by this test) stops reading
    try:
        for k in range(400):
            rec.can_frame(k, k, 0x100, b"\x01", True)
            rec.tick(k, {"tick": k})
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    rec.close()
    assert rec.error is None
    run = read_run(path)
    kept = len(run.records)
    assert kept % 8 == 0 and 0 < kept < 400
    assert [r.tick for r in run.records] == [f.tick for f in run.frames] == list(range(kept))
    assert rec.dropped == 2 * (400 - kept)


def test_close_waits_for_the_writer_instead_of_dropping_the_last_batch(
        tmp_path: Path) -> None:
    """The last batch holds the safe command of a stopping run: close() sends it even
    when the pipe is full at that moment (it waits for the writer, which resumes)."""
    path = tmp_path / "last.mcap"
    rec = recorder(path, queue_size=16, pipe_bytes=4096)
    stop_and_wait_stopped(rec.pid)        # the writer (started by this test) stops reading
    resume = threading.Timer(0.5, os.kill, (rec.pid, signal.SIGCONT))
    try:
        k = 0
        while rec.tick(k, {"tick": k}):   # fill the pipe
            k += 1
        dropped = rec.dropped
        rec.can_frame(k + 1, k + 1, 0x080, b"\x00\x00", False)   # batched, not yet sent
        resume.start()
        rec.close()
    except BaseException:
        resume.cancel()
        os.kill(rec.pid, signal.SIGCONT)
        raise
    assert rec.error is None and rec.dropped == dropped
    run = read_run(path)
    assert [(f.tick, f.arbitration_id) for f in run.frames][-1] == (k + 1, 0x080)


def test_item_larger_than_the_pipe_is_sent_in_pieces(tmp_path: Path) -> None:
    """A write the pipe takes only in part is finished by later flushes (the stream
    never tears); the ticks in between are dropped and counted."""
    path = tmp_path / "big.mcap"
    big = "x" * 200_000
    rec = recorder(path, pipe_bytes=4096)
    rec.event(0, 0, "note", big)
    sent_ok = []
    for k in range(1, 3000):
        rec.can_frame(k, k, 0x100, b"\x02", True)
        sent_ok.append(rec.tick(k, {"tick": k}))
        time.sleep(0.0002)
    rec.close()
    assert rec.error is None and rec.malformed == 0
    run = read_run(path)
    assert run.events[0].detail == big
    ok_ticks = [k for k, ok in zip(range(1, 3000), sent_ok, strict=True) if ok]
    assert ok_ticks and [r.tick for r in run.records] == ok_ticks
    assert rec.dropped == 2 * (2999 - len(ok_ticks))


def test_bad_path_raises_at_once(tmp_path: Path) -> None:
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro" / "run.mcap").mkdir()       # a directory where the file should go
    with pytest.raises(OSError, match=r"run\.mcap"):
        recorder(tmp_path / "ro" / "run.mcap")


def test_malformed_record_is_skipped_not_fatal(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with recorder(path) as rec:
        rec.tick(0, {"no_tick": 1})
        rec.tick(1, {"tick": 1, "obj": object()})
        rec.can_frame(2, 2, 0x100, b"\x02", True)
    assert rec.malformed == 2 and rec.last_malformed is not None
    assert [f.tick for f in read_run(path).frames] == [2]


def test_throughput_1khz_three_frames_one_record(tmp_path: Path) -> None:
    """Recorder load of the 1 kHz loop: 3 frames + 1 record per tick, everything written.
    The figures are printed only (timing goals live in bench/): the recorder waits for
    the writer here (``blocking``, as in offline replay), so a busy machine slows the
    test down instead of dropping batches."""
    n = 3000
    rec = recorder(tmp_path / "tp.mcap", poll_s=0.002, blocking=True)
    records = [tick_record(k) for k in range(n)]
    t0 = time.perf_counter()
    cpu0 = time.thread_time()
    for k in range(n):
        t = k * 1_000_000
        rec.can_frame(t, k, 0x100, b"\x01" * 8, True)
        rec.can_frame(t, k, 0x200, b"\x02" * 8, True)
        rec.tick(t, records[k])
        rec.can_frame(t, k, 0x080, b"\x03" * 8, False)
    enqueue_s = time.thread_time() - cpu0
    rec.close()
    total_s = time.perf_counter() - t0
    size = rec.paths[0].stat().st_size
    print(f"\nrecorder: enqueue {1e6 * enqueue_s / n:.2f} us/tick on the loop thread; "
          f"{n} ticks written in {total_s:.3f} s = {n / total_s:.0f} ticks/s "
          f"({100 * total_s / (n / 1000):.1f} % of real time at 1 kHz); "
          f"{size / n:.0f} B/tick zstd")
    run = read_run(rec.paths[0])
    assert rec.dropped == 0 and [r.tick for r in run.records] == list(range(n))
    assert len(run.frames) == 3 * n


@pytest.fixture(scope="module")
def small_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, list[tuple[str, Any]]]:
    path = tmp_path_factory.mktemp("cut") / "full.mcap"
    with recorder(path, chunk_bytes=2048) as rec:
        expected = write_mixed(rec, 60)
    return path.read_bytes(), expected


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.0, 1.0))
def test_truncated_anywhere_reads_a_prefix(tmp_path: Path, frac: float,
                                           small_run: tuple[bytes, list[tuple[str, Any]]]
                                           ) -> None:
    """Cutting the file at any byte never raises and yields a prefix of what was written."""
    blob, expected = small_run
    cut = int(frac * len(blob))
    path = tmp_path / f"cut{cut}.mcap"
    path.write_bytes(blob[:cut])
    got = timeline_of(path)
    assert got == expected[:len(got)]
    run = read_run(path)
    assert run.complete == (cut == len(blob))
    if cut < len(blob):
        assert run.stopped_at is not None and str(path) in run.stopped_at


def test_relative_path_is_the_callers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The writer process runs elsewhere; a relative path still means the caller's."""
    monkeypatch.chdir(tmp_path)
    with recorder(Path("rel.mcap")) as rec:
        rec.can_frame(1, 0, 0x100, b"\x01", True)
    assert rec.base_path == tmp_path / "rel.mcap"
    assert [f.data for f in read_run(tmp_path / "rel.mcap").frames] == [b"\x01"]


# ----------------------------------------------------------------------- packed tick records

_ENUM_NAMES = (None, "ALPHA", "BETA")
_SCALAR_ST = {
    "int": st.integers(-2**62, 2**62),
    "float": st.floats(allow_nan=False, allow_infinity=False, width=64),
    "bool": st.booleans(),
    "ns_as_s": st.integers(-5, 10**15),
    "enum": st.integers(0, len(_ENUM_NAMES) - 1),
}
_ARRAY_DTYPES = {"<f8": np.float64, "|b1": np.bool_, "<i8": np.int64, "<i4": np.int32,
                 "|u1": np.uint8}


@st.composite
def packed_records(draw: st.DrawFn) -> tuple[Any, list[tuple[list[Any], list[np.ndarray]]]]:
    from rig.recording.codec import TickLayout

    fields: list[tuple[str, str, Any]] = [("tick", "int", None)]
    for i in range(draw(st.integers(0, 6))):
        if draw(st.booleans()):
            kind = draw(st.sampled_from(sorted(_SCALAR_ST)))
            fields.append((f"s{i}", kind, _ENUM_NAMES if kind == "enum" else None))
        else:
            dt = draw(st.sampled_from(sorted(_ARRAY_DTYPES)))
            shape = tuple(draw(st.lists(st.integers(0, 4), min_size=1, max_size=2)))
            fields.append((f"a{i}", dt, shape))
    layout = TickLayout(tuple(fields))
    rows = []
    for k in range(draw(st.integers(1, 4))):
        scalars: list[Any] = [k]
        arrays: list[np.ndarray] = []
        for _, kind, extra in fields[1:]:
            if kind in _SCALAR_ST:
                scalars.append(draw(_SCALAR_ST[kind]))
            else:
                n = int(np.prod(extra))
                dtype = _ARRAY_DTYPES[kind]
                if dtype is np.float64:
                    vals = draw(st.lists(st.floats(allow_nan=False, allow_infinity=False),
                                         min_size=n, max_size=n))
                elif dtype is np.bool_:
                    vals = draw(st.lists(st.booleans(), min_size=n, max_size=n))
                else:
                    info = np.iinfo(dtype)
                    vals = draw(st.lists(st.integers(int(info.min), int(info.max)),
                                         min_size=n, max_size=n))
                arrays.append(np.array(vals, dtype=dtype).reshape(extra))
        rows.append((scalars, arrays))
    return layout, rows


def expected_packed(layout: Any, scalars: list[Any], arrays: list[np.ndarray]
                    ) -> dict[str, Any]:
    """What the record reads back as, worked out from the layout's documented meaning."""
    s_it, a_it = iter(scalars), iter(arrays)
    out: dict[str, Any] = {}
    for key, kind, extra in layout.fields:
        if kind in _SCALAR_ST:
            v = next(s_it)
            if kind == "ns_as_s":
                v = v * 1e-9 if v >= 0 else None
            elif kind == "enum":
                v = extra[v]
            out[key] = v
        else:
            out[key] = next(a_it).ravel().tolist()      # matrices flat, row-major
    # a value that cannot be a JSON number is recorded as the sentinel and its key listed
    # in "nonfinite" (docs/recording.md); read_run gives None and keeps the list
    absent = [key for key, kind, _ in layout.fields if kind == "ns_as_s" and out[key] is None]
    if absent:
        out["nonfinite"] = absent
    return out


@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(packed_records())
def test_packed_tick_records_read_back_as_declared(
        tmp_path: Path, case: tuple[Any, list[tuple[list[Any], list[np.ndarray]]]]) -> None:
    layout, rows = case
    path = tmp_path / f"packed{time.monotonic_ns()}.mcap"
    with recorder(path, tick_layout=layout) as rec:
        for k, (scalars, arrays) in enumerate(rows):
            rec.can_frame(10 * k, k, 0x100, b"\x01", True)
            assert rec.tick_values(10 * k + 1, scalars, arrays)
    assert rec.malformed == 0 and rec.error is None and rec.dropped == 0
    got = [r.data for r in read_run(path).records]
    assert got == [expected_packed(layout, s, a) for s, a in rows]


def test_packed_tick_record_rejects_a_wrong_shape(tmp_path: Path) -> None:
    from rig.recording.codec import TickLayout

    layout = TickLayout((("tick", "int", None), ("q", "<f8", (3,))))
    with recorder(tmp_path / "shape.mcap", tick_layout=layout) as rec:
        with pytest.raises(ValueError):
            rec.tick_values(0, [0], [np.zeros(4)])
        assert rec.tick_values(1, [1], [np.ones(3)])
    assert [r.data for r in read_run(tmp_path / "shape.mcap").records] == [
        {"tick": 1, "q": [1.0, 1.0, 1.0]}]


def test_a_record_packed_by_the_loop_reads_back_like_one_packed_here(tmp_path: Path) -> None:
    """``tick_packed`` (the loop packs once for the recording and the telemetry) records
    the same item as ``tick_values``; a record of another size is refused."""
    from rig.recording.codec import TickLayout, TickPacker

    layout = TickLayout((("tick", "int", None), ("q", "<f8", (3,))))
    packer = TickPacker(layout)
    path = tmp_path / "packed_by_loop.mcap"
    with recorder(path, tick_layout=layout) as rec:
        packer.pack(1, [1], [np.arange(3.0)])
        assert rec.tick_packed(packer.buffer)
        assert rec.tick_values(2, [2], [np.arange(3.0)])
        with pytest.raises(ValueError):
            rec.tick_packed(packer.buffer[:-8])
    assert [r.data for r in read_run(path).records] == [
        {"tick": 1, "q": [0.0, 1.0, 2.0]}, {"tick": 2, "q": [0.0, 1.0, 2.0]}]


def test_a_dropped_batch_keeps_its_tick_layout(tmp_path: Path) -> None:
    """The layout declared while the pipe is full is kept back like an event: the packed
    records sent once the writer catches up still decode."""
    from rig.recording.codec import TickLayout

    path = tmp_path / "layout.mcap"
    rec = recorder(path, pipe_bytes=4096)
    stop_and_wait_stopped(rec.pid)        # the writer (started by this test) stops reading
    try:
        for k in range(200):              # fill the pipe
            rec.tick(k, {"tick": k})
        rec.set_tick_layout(TickLayout((("tick", "int", None), ("x", "float", None))))
        assert rec.tick_values(1000, [1000, 0.5], []) is False      # dropped with its batch
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    sent = []
    for k in range(1001, 3000):
        if rec.tick_values(k, [k, 1.5], []):
            sent.append(k)
        if len(sent) >= 3:
            break
        time.sleep(0.001)
    rec.close()
    assert rec.malformed == 0 and rec.error is None
    packed = [r.data for r in read_run(path).records if r.tick >= 1000]
    assert packed == [{"tick": k, "x": 1.5} for k in sent]
