"""Hostile bytes in recordings and configuration files (issue 25): every defect is
refused in one line naming what is wrong (tests/support/one_line.py), and a refused
command leaves no partial output behind."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from controller.config import default_config
from tests.support.mcap_edit import chunk_spans, rewrite
from tests.support.one_line import one_line

pytestmark = pytest.mark.timeout(300)
CFG = default_config()


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory, design_path: Path) -> Path:
    from hil.stepped_run import record_emulated_run

    return record_emulated_run(tmp_path_factory.mktemp("hostile") / "run.mcap", 0.3,
                               cfg=CFG, design_bytes=design_path.read_bytes())


# ---------------------------------------------------------------------------- report

def _never_fresh(data: bytes) -> bytes:
    """A tick record of a loop that never received SensorData (nobody on the bus)."""
    obj = json.loads(data)
    obj.update(sensor_age_ticks=obj["tick"] + 1, rattlespace_m=0.0, sprung_accel_mps2=0.0,
               force_meas_n=0.0, sensor_counter=0)
    return json.dumps(obj).encode()


def _no_partial_output(parent: Path, name: str) -> None:
    assert not (parent / name).exists()
    assert not [p for p in parent.iterdir() if ".partial-" in p.name]


def test_report_without_sensor_data_is_refused_and_writes_nothing(
        recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = rewrite(recording, tmp_path / "norig.mcap", "/rig/signals", _never_fresh,
                  every=True)
    one_line(["report", str(bad)], capsys, "norig.mcap: no sensor data:",
             "none with a fresh SensorData reading", "nothing to report")
    _no_partial_output(tmp_path, "norig-report")


def test_report_failing_half_way_leaves_no_partial_directory(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import rig.report.page as page
    from rig.report import write_report

    def half_way(d: Any, out: Path) -> Any:
        (out / "rattlespace.png").write_bytes(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(page, "render_all", half_way)
    with pytest.raises(OSError, match="No space"):
        write_report(recording, tmp_path / "out")
    _no_partial_output(tmp_path, "out")
    # an existing output directory keeps its files when a later report fails
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "index.html").write_text("earlier report")
    with pytest.raises(OSError, match="No space"):
        write_report(recording, tmp_path / "out")
    assert (tmp_path / "out" / "index.html").read_text() == "earlier report"
    assert not (tmp_path / "out" / "rattlespace.png").exists()


def test_report_replaces_the_files_of_an_existing_directory(recording: Path,
                                                            tmp_path: Path) -> None:
    from rig.report import write_report

    out = tmp_path / "out"
    out.mkdir()
    (out / "index.html").write_text("earlier report")
    (out / "notes.txt").write_text("mine")
    index = write_report(recording, out)
    assert index == out / "index.html" and "Run report" in index.read_text()
    assert (out / "notes.txt").read_text() == "mine" and (out / "force.png").exists()
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


# ---------------------------------------------------------------------------- huge integers

HUGE = "1" * 5000
HUGE_HEX = "0x" + "f" * 4000


@pytest.mark.parametrize(("text", "fragments"), [
    (f"[sensors]\nseed = {HUGE}\n",
     ("config key 'sensors.seed'", "more than 4300 digits on line 2",
      "allowed an integer of at most 4300 digits")),
    (f"[sensors]\nseed = {HUGE_HEX}\n",
     ("config key 'sensors.seed'", "<an integer of about 4817 digits>")),
    (f"[design]\nweight_sets = [[1, 2,\n  {HUGE}]]\n",
     ("config key 'design.weight_sets'", "on line 3")),
    (f"[design]\nweight_sets = [[{HUGE_HEX}, 1, 1, 1]]\n",
     ("config key 'design.weight_sets[0][0]'", "a finite number")),
    (f"x = {HUGE_HEX}\n", ("config key 'x'", "a known key")),
])
def test_huge_integer_in_a_config_names_the_key(text: str, fragments: tuple[str, ...],
                                                tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "huge.toml"
    path.write_text(text)
    err = one_line(["sim", "--config", str(path)], capsys, *fragments)
    assert len(err) < 400


@pytest.fixture(scope="module")
def huge_seed_recording(recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from controller.config import config_to_toml

    toml = config_to_toml(CFG).replace("[sensors]\n", f"[sensors]\nseed = {HUGE}\n#", 1)
    return rewrite(recording, tmp_path_factory.mktemp("huge") / "huge.mcap",
                   "/rig/signals", lambda d: d,
                   attachments={"config.toml": toml.encode()})


@pytest.mark.parametrize("command", ["replay", "identify"])
def test_huge_integer_in_a_recorded_config_names_the_key(
        command: str, huge_seed_recording: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    one_line([command, str(huge_seed_recording)], capsys, "huge.mcap",
             "config.toml", "config key 'sensors.seed'", "more than 4300 digits")


def test_report_of_a_recorded_config_with_a_huge_integer_names_it(
        huge_seed_recording: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    from rig.cli import main

    out = tmp_path / "rep"
    assert main(["report", str(huge_seed_recording), "--out", str(out)]) == 0
    assert capsys.readouterr().err == ""
    page = (out / "index.html").read_text()
    assert "config key &#x27;sensors.seed&#x27;" in page and "4300 digits" in page


# ---------------------------------------------------------------------------- terminal text

def test_safe_escapes_control_characters_and_caps_the_length() -> None:
    from rig.terminal import MAX_ECHO_CHARS, safe

    assert safe("a\nb\x1b[2J\r\t\x7f\x9b\u2028\u202e\ufeffc") == \
        "a\\nb\\x1b[2J\\r\\t\\x7f\\x9b\\u2028\\u202e\\ufeffc"
    assert safe("r\xe9seau \u00fc \u4e2d") == "r\xe9seau \u00fc \u4e2d"
    long = safe("k" * 7_000_000)
    assert len(long) < MAX_ECHO_CHARS + 40 and long.endswith("[6999000 more characters]")
    assert len(safe("\x1b" * 5000)) < MAX_ECHO_CHARS + 40


@pytest.mark.parametrize(("key", "shown"), [
    ('"a\\nb\\u001b[2J"', "a\\nb\\x1b[2J"),
    ('"' + "k" * 7_000_000 + '"', "more characters]"),
])
def test_a_hostile_config_key_is_echoed_escaped_and_short(
        key: str, shown: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "hostile.toml"
    path.write_text(f"{key} = 1\n")
    err = one_line(["sim", "--config", str(path)], capsys, "rig sim: config key", shown)
    assert "\x1b" not in err and len(err) < 1100


def test_a_hostile_file_name_is_echoed_escaped(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x\x1b[2J\ny.mcap"
    bad.write_bytes(b"not a recording at all")
    err = one_line(["replay", str(bad)], capsys, "x\\x1b[2J\\ny.mcap", "not an MCAP file")
    assert "\x1b" not in err
    err = one_line(["report", str(tmp_path / "nope\x1b.mcap"), "--compare",
                    str(tmp_path / "gone\x07.mcap")], capsys, "gone\\x07.mcap")
    assert "\x07" not in err


# ---------------------------------------------------------------------------- FIFOs

FIFO_CASES = [
    (["sim", "--config", "{fifo}"], "a readable TOML file (it is a FIFO (named pipe)"),
    (["hil", "--faults", "{fifo}"], "FIFO"),
    (["sim", "--road", "csv:{fifo}"], "road file"),
    (["replay", "{fifo}"], "fifo.mcap: is a FIFO (named pipe), expected a regular file"),
    (["replay", "{fifo_log}"], "fifo.log: is a FIFO (named pipe)"),
    (["report", "{fifo}"], "fifo.mcap: is a FIFO (named pipe)"),
    (["identify", "{fifo}"], "is a FIFO (named pipe)"),
    (["replay", "{rec}", "--design", "{fifo}"], "--design"),
    (["report", "{rec}", "--compare", "{fifo}"], "--compare"),
    (["replay", "/dev/zero"], "is a character device, expected a regular file"),
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("argv", "fragment"), FIFO_CASES,
                         ids=[" ".join(a) for a, _ in FIFO_CASES])
def test_a_fifo_is_refused_without_blocking(argv: list[str], fragment: str, recording: Path,
                                            tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    import os

    names = {"fifo": tmp_path / "fifo.mcap", "fifo_log": tmp_path / "fifo.log",
             "rec": recording}
    os.mkfifo(names["fifo"])
    os.mkfifo(names["fifo_log"])
    one_line([a.format(**{k: str(v) for k, v in names.items()}) for a in argv], capsys,
             fragment)


# ---------------------------------------------------------------------------- attachment CRC

def _damaged_config(recording: Path, dst: Path, *, cut: bool) -> Path:
    """``recording`` with one byte of its config.toml attachment changed (the attachment
    record's CRC left as it was); ``cut``: truncated in the middle of its last chunk (no
    summary, no data CRC)."""
    raw = bytearray(recording.read_bytes())
    i = raw.index(b"stale_ticks = ") + len(b"stale_ticks = ")
    raw[i] = ord("9") if raw[i] != ord("9") else ord("8")
    start, end = chunk_spans(recording)[-1]
    dst.write_bytes(raw[:(start + end) // 2] if cut else raw)
    return dst


@pytest.mark.parametrize("cut", [True, False], ids=["truncated", "whole"])
def test_a_damaged_config_attachment_is_named_not_replayed(
        cut: bool, recording: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    bad = _damaged_config(recording, tmp_path / "stale.mcap", cut=cut)
    for command in ("replay", "identify"):
        one_line([command, str(bad)], capsys, "stale.mcap",
                 "attachment", "config.toml", "is damaged (CRC mismatch in its "
                 "Attachment record at byte")


def test_report_names_a_damaged_config_attachment(recording: Path, tmp_path: Path) -> None:
    from rig.report import load_series

    s = load_series(_damaged_config(recording, tmp_path / "stale.mcap", cut=True))
    assert s.config is None and "config.toml attachment is damaged (CRC" in s.config_problem
    assert "config.toml" not in s.scan.attachments
    assert any("attachment 'config.toml' damaged" in n for n in s.scan.notes)


# ---------------------------------------------------------------------------- full disk

def _limited_file_size(limit: int) -> Any:
    """preexec_fn: files written by the process (and its writer child) stop at ``limit``
    bytes with EFBIG, as on a full disk (SIGXFSZ ignored: the write fails instead)."""
    import resource
    import signal

    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_replay_out_on_a_full_disk_says_so_and_exits_3(recording: Path,
                                                        tmp_path: Path) -> None:
    """The disk fills half-way through the replay's records: the limit is the middle of
    the recorded run's chunks (the replay writes the same attachments and ticks;
    :func:`tests.support.mcap_edit.chunk_spans`)."""
    import os
    import subprocess
    import sys

    spans = chunk_spans(recording)
    assert len(spans) >= 2
    limit = (spans[0][0] + spans[-1][1]) // 2
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "out.mcap"
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "replay", str(recording),
                           "--out", str(out), "--json"],
                          env={**os.environ, "PYTHONPATH": str(root)}, cwd=tmp_path,
                          capture_output=True, text=True, timeout=120,
                          preexec_fn=_limited_file_size(limit))
    assert proc.returncode == 3, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert f"rig replay: {out} is incomplete: recording to {out} failed:" in proc.stderr
    assert "File too large" in proc.stderr
    summary = json.loads(proc.stdout)
    assert "File too large" in summary["out_error"] and summary["bit_exact"]


def test_replay_without_out_writes_no_file(recording: Path, tmp_path: Path) -> None:
    """Replay reads the recorded design from memory: with no file writable at all (a file
    size limit of 0 bytes) a replay without --out still runs and is bit-exact."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "replay", str(recording),
                           "--json"],
                          env={**os.environ, "PYTHONPATH": str(root)}, cwd=tmp_path,
                          capture_output=True, text=True, timeout=120,
                          preexec_fn=_limited_file_size(0))
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["bit_exact"]


def test_a_damaged_design_artifact_is_one_line(tmp_path: Path) -> None:
    """A cut artifact, in memory or as a file, is a DesignMismatch naming it, not a
    zipfile traceback."""
    from controller.artifact import DesignMismatch, design_from_bytes, load_design, save_design
    from controller.config import one_layer
    from controller.design import design_bank

    path = tmp_path / "d.npz"
    save_design(design_bank(one_layer(default_config())), path)
    raw = path.read_bytes()
    assert design_from_bytes(raw).n_models == 4
    cut = tmp_path / "cut.npz"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DesignMismatch, match=r"^attachment: not a design artifact"):
        design_from_bytes(raw[: len(raw) // 2], "attachment")
    with pytest.raises(DesignMismatch, match=rf"^{cut}: not a design artifact"):
        load_design(cut)


def _failing_close(monkeypatch: pytest.MonkeyPatch) -> None:
    from rig.recording.recorder import RunRecorder

    real = RunRecorder.close

    def close(self: RunRecorder, timeout_s: float = 30.0) -> None:
        real(self, timeout_s)
        self.error = self.error or "[Errno 28] No space left on device"
    monkeypatch.setattr(RunRecorder, "close", close)


def test_run_with_a_failed_recording_says_so_and_exits_3(
        design_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from rig.cli import main

    _failing_close(monkeypatch)
    rec = tmp_path / "run.mcap"
    rc = main(["run", "--interface", "virtual", "--channel", "full-disk", "--design",
               str(design_path), "--no-telemetry", "--no-realtime", "--duration", "0.3",
               "--record", str(rec)])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert (f"rig run: recording {rec} FAILED, it is incomplete: [Errno 28] No space left "
            "on device") in err.splitlines()[-1]


def test_demo_with_a_failed_recording_says_so(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    from rig.cli import main

    _failing_close(monkeypatch)
    rec = tmp_path / "demo.mcap"
    rc = main(["demo", "--duration", "1", "--no-telemetry", "--no-realtime", "-q",
               "--record", str(rec)])
    out = capsys.readouterr().out
    assert rc == 3
    assert f"recording: recording {rec} FAILED, it is incomplete: [Errno 28]" in out
    assert f"recording: {rec}\n" not in out


# ---------------------------------------------------------------------------- identify, cut

def test_identify_on_a_cut_recording_says_it_is_incomplete(
        identification_run: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    from rig.cli import main

    raw = identification_run.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[:int(len(raw) * 0.9)])
    assert main(["identify", str(cut), "--json"]) == 0
    state = json.loads(capsys.readouterr().out)["recording"]
    assert state["complete"] is False and "cut.mcap: truncated at byte" in state["stopped_at"]
    assert state["excitation_ended"] is False
    fitted = tmp_path / "fitted.toml"
    assert main(["identify", str(cut), "--out", str(fitted)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("INCOMPLETE RECORDING: ") and "no end event" in out.splitlines()[0]
    assert "# INCOMPLETE RECORDING: " in fitted.read_text()


# ---------------------------------------------------------------------------- road profiles

def test_a_byte_order_mark_keeps_the_first_row(tmp_path: Path) -> None:
    from hil.sim.roads import _read_csv

    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf0,0.05\n10,0\n20,0\n")
    dist, height = _read_csv(str(p))
    assert list(dist) == [0.0, 10.0, 20.0] and height[0] == 0.05
    p.write_bytes(b"\xef\xbb\xbfdistance_m,height_m\n0,0.05\n10,0\n")
    assert list(_read_csv(str(p))[0]) == [0.0, 10.0]


@pytest.mark.parametrize("height", ["1e300", "-11", "1e5"])
def test_non_physical_road_heights_are_refused(height: str, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "tall.csv"
    p.write_text(f"0,0\n1,{height}\n100,0\n")
    one_line(["sim", "--road", f"csv:{p}", "--duration", "1"], capsys,
             "line 2: height", "allowed [-10, 10] m")


def test_a_run_reads_only_the_rows_it_needs(tmp_path: Path) -> None:
    import time
    import tracemalloc

    from hil.sim.roads import make_road

    p = tmp_path / "long.csv"
    rows = 400_000                                  # 4 km at 1 cm, ~8 MB
    with p.open("w") as f:
        f.write("distance_m,height_m\n")
        f.writelines(f"{i * 0.01:.2f},{0.001 * (i % 7)}\n" for i in range(rows))
        f.write("not,a,row\n")                      # never reached by a short run
    tracemalloc.start()
    t0 = time.perf_counter()
    road = make_road(f"csv:{p}", 10.0, 2.0, 1e-3)   # needs 20 m = 2,001 rows
    elapsed = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert road.n_ticks == 2000 and elapsed < 2.0 and peak < 2_000_000, (elapsed, peak)


# ---------------------------------------------------------------------------- demo summary

def test_demo_table_says_n_a_with_the_reason() -> None:
    from rig.commands.demo import _table, ratio

    short = _table({"ticks": 0.0}, {"ticks": 1.0})
    assert "nan" not in short and "n/a: too short" in short
    assert "too short to measure (passive 0 ticks, active 1 ticks" in short
    passive = {"ticks": 1500.0, "absorbed_power": 2.9e-33, "rattlespace_rms_m": 1e-19,
               "tire_load_rms_ratio": 0.0}
    active = {"ticks": 2500.0, "absorbed_power": 0.0616, "rattlespace_rms_m": 0.0076,
              "tire_load_rms_ratio": 0.12}
    flat = _table(passive, active)
    assert "e+" not in flat and "n/a: passive flat" in flat
    assert ratio(passive, active, "absorbed_power") == (None, "n/a: passive flat")
    assert ratio({"absorbed_power": 0.5}, {"absorbed_power": 0.1}, "absorbed_power") == \
        (pytest.approx(0.2), "")
