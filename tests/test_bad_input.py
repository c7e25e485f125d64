"""Bad input on the command line: every subcommand answers a bad argument, configuration
or input file with ONE line on stderr naming what is wrong and what is allowed, exit
status 2, no traceback, nothing written (rig/argtypes.py, rig/output_paths.py,
controller/config.py).  ``--json`` output is strict JSON (rig/strict_json.py).

Most cases run ``rig.cli.main`` in-process (argument checks happen before anything is
opened or computed, so they are fast); a few run the real console program in a
subprocess to show the same from the outside."""

from __future__ import annotations

import contextlib
import gc
import io
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from controller.config import config_to_toml, default_config
from rig import argtypes, strict_json
from rig.cli import SUBCOMMANDS, build_parser, main
from tests.support.mcap_edit import rewrite

pytestmark = pytest.mark.timeout(300)
ROOT = Path(__file__).resolve().parents[1]
CFG = default_config()


# ---------------------------------------------------------------------------- files

@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad-input")
    f: dict[str, Path] = {"dir": d}
    f["utf8"] = d / "latin1.toml"
    f["utf8"].write_bytes('[can]\nchannel = "r\xe9seau"\n'.encode("latin-1"))
    f["nested"] = d / "nested.toml"
    f["nested"].write_text("a = " + "[" * 3000 + "]" * 3000 + "\n")
    f["grid"] = d / "grid.toml"
    f["grid"].write_text("[design]\nlinearisation_deflections_m = ["
                         + ",".join(f"{0.001 + i * 1e-7:.7f}" for i in range(200_000))
                         + "]\n")
    f["existing"] = d / "existing.npz"
    f["existing"].write_bytes(b"an earlier result")
    f["existing_mcap"] = d / "earlier.mcap"
    f["existing_mcap"].write_bytes(b"an earlier recording")
    (d / "rotated.001.mcap").write_bytes(b"segment of an earlier run")
    f["rotated"] = d / "rotated.mcap"           # itself deleted, its segment is there
    f["junk"] = d / "junk.npz"
    f["junk"].write_bytes(b"junk\n")
    f["short_csv"] = d / "short.csv"
    f["short_csv"].write_text("distance_m,height_m\n0,0\n1,0.01\n")
    f["nan_log"] = d / "nan.log"
    f["nan_log"].write_text("(1.000000) vcan0 100#0011223344556677\n"
                            "(nan) vcan0 100#0011223344556677\n")
    f["far_log"] = d / "far.log"
    f["far_log"].write_text("(1.000000) vcan0 100#0011223344556677\n"
                            "(1e300) vcan0 100#0011223344556677\n")
    f["ok_log"] = d / "ok.log"
    f["ok_log"].write_text("(1.000000) vcan0 100#0011223344556677\n"
                           "(1.200000) vcan0 100#0011223344556677\n")
    f["nested_json"] = d / "faults.json"
    f["nested_json"].write_text("[" * 5000 + "]" * 5000)
    f["nan_json"] = d / "nan-faults.json"
    f["nan_json"].write_text('[[NaN, 1.0, "silence"]]')
    f["three_sets"] = d / "three.toml"
    f["three_sets"].write_text(config_to_toml(CFG.replace(
        design={"weight_sets": [*CFG.design.weight_sets, [1.0, 1.0, 1e-8, 1.0]]})))
    return f


@pytest.fixture(scope="module")
def design_file(design_path: Path) -> Path:
    return design_path


@pytest.fixture(scope="module")
def recording(files: dict[str, Path], design_file: Path) -> Path:
    from hil.stepped_run import record_emulated_run

    return record_emulated_run(files["dir"] / "run.mcap", 0.3, cfg=CFG,
                               design_bytes=design_file.read_bytes())


def _without(*keys: str) -> Any:
    def change(data: bytes) -> bytes:
        obj = json.loads(data)
        for k in keys:
            obj.pop(k, None)
        return json.dumps(obj).encode()
    return change


# ---------------------------------------------------------------------------- the check

def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str],
                     *fragments: str) -> str:
    rc = main(argv)
    gc.collect()                 # a leaked python-can bus would log a second line now
    out, err = capsys.readouterr()
    assert rc == 2, (rc, err)
    assert "Traceback" not in err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith("rig"), err
    for frag in fragments:
        assert frag in err, (frag, err)
    assert out == ""
    return err


# ---------------------------------------------------------------------------- configuration

CONFIG_CASES = {
    "utf8": "byte 0xe9 at offset",
    "nested": "nested at most",
    "grid": "at most 64 entries (one linear tire model each",
    "missing": "a readable TOML file",
    "dir": "a readable TOML file",
}


@pytest.mark.parametrize("command", list(SUBCOMMANDS))
@pytest.mark.parametrize("case", list(CONFIG_CASES))
def test_bad_config_file_on_every_subcommand(command: str, case: str,
                                            files: dict[str, Path],
                                            capsys: pytest.CaptureFixture[str]) -> None:
    path = files["dir"] / "missing.toml" if case == "missing" else files[case]
    err = _one_line_exit_2([command, "--config", str(path)], capsys, CONFIG_CASES[case])
    assert f"rig {command}: config key" in err


def test_dev_zero_as_config_is_refused_without_reading_it(
        capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["design", "--config", "/dev/zero", "--out", "x.npz"], capsys,
                     "it is a character device, expected a regular file")


# ---------------------------------------------------------------------------- arguments

#: (argv, fragments of the one line); argv may hold {name} placeholders for ``files``
ARGUMENT_CASES: list[tuple[list[str], tuple[str, ...]]] = [
    # parser-level
    ([], ("required: COMMAND",)),
    (["nope"], ("invalid choice: 'nope'",)),
    (["demo", "--nope"], ("rig demo: unrecognized arguments: --nope",)),
    (["demo", "--duration"], ("--duration: expected one argument",)),
    (["sim", "--controller", "pid"], ("invalid choice: 'pid'",)),
    (["design"], ("required: --out",)),
    (["replay"], ("required: RUN",)),
    # durations: finite, > 0, bounded
    *[([cmd, "--duration", v], ("--duration", why))
      for cmd in ("demo", "run", "hil", "sim", "montecarlo")
      for v, why in (("inf", "not a finite number"), ("nan", "not a finite number"),
                     ("1e300", "out of range"), ("0", "out of range"),
                     ("-1", "out of range"), ("abc", "not a number"))],
    # speeds: the configuration's noise.nominal_speed_mps range
    *[([cmd, "--speed", v], ("--speed", "allowed [0.1, 100] m/s"))
      for cmd in ("demo", "sim", "montecarlo", "hil") for v in ("1e300", "nan", "0", "-5")],
    # weight sets: 0 (the travel schedule) and 1..len(design.weight_sets)
    *[([cmd, opt, v], (opt, "allowed 0..2"))
      for cmd, opt in (("demo", "--weights"), ("run", "--weights"), ("demo", "--weight-set"),
                       ("analyze", "--weights"), ("sim", "--weights"),
                       ("montecarlo", "--weights")) for v in ("-1", "3", "one")],
    (["demo", "--config", "{three_sets}", "--weights", "4"], ("allowed 0..3",)),
    # controller modes: the names of controller.modes
    *[([cmd, "--controller", "kalman"], ("--controller", "invalid choice", "fuzzy"))
      for cmd in ("demo", "run", "sim", "montecarlo")],
    # seeds: non-negative 64-bit
    *[([cmd, "--seed", v], ("--seed", "[0, 9223372036854775807]"))
      for cmd in ("demo", "sim", "montecarlo", "hil") for v in ("-1", str(2**64))],
    # roads, checked at parse time
    *[([cmd, "--road", road], ("--road", frag))
      for cmd in ("demo", "sim", "montecarlo", "hil")
      for road, frag in (("nope", "unknown road 'nope'"),
                         ("csv:{dir}/missing.csv", "is not readable"),
                         ("csv:{junk}", "needs at least two"))],
    # other numbers
    (["demo", "--max-rearms", "-1"], ("--max-rearms", "[0, 1000]")),
    (["hil", "--watchdog-ms", "inf"], ("--watchdog-ms", "not a finite number")),
    (["hil", "--watchdog-ms", "0"], ("--watchdog-ms", "(0, 60000] ms")),
    (["hil", "--rt-priority", "1000"], ("--rt-priority", "out of range")),
    (["run", "--rt-priority", "-1"], ("--rt-priority", "out of range")),
    (["run", "--cpu", "99999"], ("--cpu", "this machine has CPUs 0..")),
    (["sim", "--delay", "-1"], ("--delay", "[0, 1000] ticks")),
    (["sim", "--rate", "nan"], ("--rate", "[50, 20000] Hz")),
    (["montecarlo", "--runs", "0"], ("--runs", "[1, 10000]")),
    (["montecarlo", "--runs", "1e3"], ("--runs", "not an integer")),
    (["montecarlo", "--spread", "nan"], ("--spread", "[0, 0.5]")),
    (["montecarlo", "--jobs", "0"], ("--jobs", "[1, 1024]")),
    (["montecarlo", "--ride-height-std", "-1"], ("--ride-height-std", "[0, 0.05] m")),
    (["study", "--jobs", "0"], ("--jobs", "[1, 1024]")),
    (["replay", "{ok_log}", "--arm-at", "nan"], ("--arm-at", "not a finite number")),
    (["replay", "{ok_log}", "--arm-at", "-1"], ("--arm-at", "out of range")),
    (["replay", "{existing_mcap}", "--arm-at", "1"], ("--arm-at applies to log files",)),
    # input files
    (["run", "--design", "{dir}/missing.npz"], ("--design", "no such file")),
    (["run", "--design", "{dir}"], ("--design", "is a directory")),
    (["run", "--design", "{junk}", "--interface", "virtual", "--no-record",
      "--no-telemetry", "--no-realtime"], ("design artifact", "not a design artifact")),
    (["replay", "{ok_log}", "--design", "{dir}/missing.npz"], ("no such file",)),
    (["hil", "--faults", "{dir}/missing.toml"], ("--faults", "no such file")),
    (["hil", "--faults", "{utf8}"], ("UTF-8",)),
    (["hil", "--faults", "{nested_json}"], ("nested at most",)),
    (["hil", "--faults", "{nan_json}"], ("NaN is not a number",)),
    (["report", "{existing_mcap}", "--compare", "{dir}/missing.mcap"], ("no such file",)),
    # outputs: single files need --force, recordings are never overwritten,
    # output directories must not be files
    (["design", "--out", "{existing}"], ("exists: add --force",)),
    (["design", "--out", "{dir}"], ("is a directory",)),
    (["design", "--out", "/proc/nope/x.npz"], ("directory /proc/nope does not exist",)),
    (["sim", "--traces", "{existing}"], ("exists: add --force",)),
    *[([cmd, opt, target], (opt, frag))
      for cmd, opt in (("run", "--record"), ("demo", "--record"), ("replay", "--out"))
      for target, frag in (("{existing_mcap}", "a recording is never overwritten"),
                           ("{rotated}", "rotation segment rotated.001.mcap exists"),
                           ("{existing}", "is not a directory"),
                           ("/proc/nope/x.mcap", "cannot be created"))],
    *[([cmd, "--out", "{existing}"], ("--out", "is not a directory"))
      for cmd in ("montecarlo", "study", "report")],
]


def _fill(argv: list[str], files: dict[str, Path]) -> list[str]:
    return [a.format(**{k: str(v) for k, v in files.items()}) for a in argv]


def _case_id(case: tuple[list[str], tuple[str, ...]]) -> str:
    return " ".join(case[0]) or "(nothing)"


@pytest.mark.parametrize("case", ARGUMENT_CASES, ids=[_case_id(c) for c in ARGUMENT_CASES])
def test_bad_argument_is_one_line_exit_2(case: tuple[list[str], tuple[str, ...]],
                                         files: dict[str, Path],
                                         capsys: pytest.CaptureFixture[str]) -> None:
    argv, fragments = case
    argv = _fill(argv, files)
    before = {p: p.read_bytes() for p in (files["existing"], files["existing_mcap"])}
    _one_line_exit_2(argv, capsys, *fragments)
    assert {p: p.read_bytes() for p in before} == before      # nothing overwritten


def test_weight_set_range_follows_the_config(files: dict[str, Path]) -> None:
    argtypes.bind_config(None)
    parser = build_parser("analyze")
    with contextlib.redirect_stderr(io.StringIO()), pytest.raises(SystemExit):
        parser.parse_args(["analyze", "--weights", "3"])
    from controller.config import load_config

    argtypes.bind_config(load_config(files["three_sets"]))
    try:
        assert parser.parse_args(["analyze", "--weights", "3"]).weights == 3
    finally:
        argtypes.bind_config(None)


def test_force_replaces_a_design_artifact(files: dict[str, Path],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = files["dir"] / "replaced.npz"
    out.write_bytes(b"old")
    assert main(["design", "--out", str(out)]) == 2
    assert "add --force" in capsys.readouterr().err and out.read_bytes() == b"old"
    assert main(["design", "--out", str(out), "--force"]) == 0
    assert out.read_bytes()[:2] == b"PK"


def test_help_still_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--help"]) == 0
    assert "--duration" in capsys.readouterr().out


# ---------------------------------------------------------------------------- runtime inputs

def test_csv_road_too_short_for_the_run(files: dict[str, Path],
                                        capsys: pytest.CaptureFixture[str]) -> None:
    for cmd in ("demo", "sim"):
        _one_line_exit_2([cmd, "--road", f"csv:{files['short_csv']}", "--duration", "1",
                          "--no-telemetry", "--no-record", "--no-realtime", "-q"]
                         if cmd == "demo" else
                         [cmd, "--road", f"csv:{files['short_csv']}", "--duration", "1"],
                         capsys, "covers 1.0 m but the run needs")


@pytest.mark.parametrize(("log", "fragment"), [
    ("nan_log", "frame 2 (ID 0x100) has the time nan: every frame needs a finite timestamp"),
    ("far_log", "a replayed log may span at most 21600 s"),
])
def test_candump_log_with_a_bad_time(log: str, fragment: str, files: dict[str, Path],
                                     design_file: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["replay", str(files[log]), "--design", str(design_file)], capsys,
                     fragment)


def test_arm_at_after_the_log_is_noted(files: dict[str, Path], design_file: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(files["ok_log"]), "--design", str(design_file),
                 "--arm-at", "5"]) == 0
    assert "not armed: arm_at_s = 5 s is after the log's last tick" in \
        capsys.readouterr().out


@pytest.mark.parametrize(("topics", "change", "fragment"), [
    (("/rig/signals", "/controller/internals", "/rig/timing"), _without("tick"),
     "message 0 (sequence"),
    (("/rig/signals", "/controller/internals", "/rig/timing"),
     lambda d: json.dumps({**json.loads(d), "tick": "x"}).encode(), "not a 64-bit integer"),
    (("/rig/events",), _without("tick"), "/rig/events message 0"),
    (("/rig/signals",), lambda d: b"[1, 2]", "is a JSON list, expected an object"),
    (("/rig/signals",), lambda d: b"\xff{", "payload is not JSON"),
    (("/rig/signals",), lambda d: d + d, "messages hold"),
])
def test_report_on_a_malformed_payload(topics: tuple[str, ...], change: Any, fragment: str,
                                       recording: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = recording
    for i, topic in enumerate(topics):
        path = rewrite(path, tmp_path / f"bad{i}.mcap", topic, change)
    _one_line_exit_2(["report", str(path), "--out", str(tmp_path / "report")], capsys,
                     "rig report:", fragment)
    assert not (tmp_path / "report" / "index.html").exists()


def test_report_tolerates_ill_typed_values(recording: Path, tmp_path: Path) -> None:
    from rig.report import load_series

    bad = rewrite(recording, tmp_path / "bad.mcap", "/controller/internals",
                   lambda d: json.dumps({**json.loads(d), "q": 5,
                                         "firing_weight": {"a": 1}}).encode())
    s = load_series(bad)
    assert np.isnan(s.per_model["q"][0]).all() and s.tick.size > 100


def test_run_names_the_recording_path_not_the_bus(files: dict[str, Path], design_file: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A recording path that only fails when the recorder starts (the argument check is
    bypassed here): the message is about the recording and the bus is closed again."""
    monkeypatch.setattr(argtypes, "recording_target", str)
    err = _one_line_exit_2(["run", "--interface", "virtual", "--channel", "bad-rec",
                            "--design", str(design_file), "--no-telemetry", "--no-realtime",
                            "--duration", "1", "--record", "/proc/nope/x.mcap"],
                           capsys, "cannot record to /proc/nope/x.mcap")
    assert "CAN bus" not in err


def test_recorder_never_overwrites(files: dict[str, Path], tmp_path: Path) -> None:
    from datetime import UTC, datetime

    from rig.output_paths import recording_file
    from rig.recording.recorder import RecorderStartError, RunRecorder

    for target, frag in ((files["existing_mcap"], "never overwritten"),
                         (files["rotated"], "rotated.001.mcap exists")):
        before = target.read_bytes() if target.exists() else None
        with pytest.raises(RecorderStartError, match=frag):
            RunRecorder(target, CFG.recording, config_toml="", design_bytes=None,
                        metadata={})
        assert (target.read_bytes() if target.exists() else None) == before
    now = datetime(2030, 1, 2, 3, 4, 5, tzinfo=UTC)
    first = recording_file(tmp_path, now)
    assert first.name == "run-20300102T030405Z.mcap"
    first.write_bytes(b"x")
    assert recording_file(tmp_path, now).name == "run-20300102T030405Z-2.mcap"


# ---------------------------------------------------------------------------- real processes

@pytest.mark.parametrize(("argv", "fragment"), [
    # refused before the bus is opened: with a bus that does not exist, the message is
    # still about --duration
    (["run", "--interface", "socketcan", "--channel", "nosuchcan9", "--duration", "inf",
      "--no-record", "--no-telemetry"], "--duration: inf is not a finite number"),
    (["demo", "--weights", "3"], "--weights: 3 is not a weight set"),
    (["demo", "--speed", "1e300"], "--speed: 1e300 is out of range"),
    (["hil", "--config", "{utf8}"], "UTF-8"),
    (["design", "--config", "{nested}", "--out", "x.npz"], "nested at most"),
])
def test_real_cli_process_one_line(argv: list[str], fragment: str,
                                   files: dict[str, Path]) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "rig.cli", *_fill(argv, files)],
                          cwd=files["dir"], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and fragment in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


# ---------------------------------------------------------------------------- properties

#: (command, option, lo, hi): every numeric option with its allowed closed-or-open range
NUMERIC_OPTIONS = [
    ("demo", "--duration", 0.0, argtypes.MAX_OFFLINE_S),
    ("demo", "--speed", 0.1, 100.0),
    ("sim", "--duration", 0.0, argtypes.MAX_OFFLINE_S),
    ("sim", "--speed", 0.1, 100.0),
    ("sim", "--rate", 50.0, 20000.0),
    ("montecarlo", "--spread", 0.0, 0.5),
    ("montecarlo", "--ride-height-std", 0.0, 0.05),
    ("hil", "--duration", 0.0, argtypes.MAX_SERVICE_S),
    ("hil", "--watchdog-ms", 0.0, 60_000.0),
    ("run", "--duration", 0.0, argtypes.MAX_SERVICE_S),
    ("replay", "--arm-at", 0.0, 21600.0),
]
_PARSERS = {cmd: build_parser(cmd) for cmd in {c for c, *_ in NUMERIC_OPTIONS}}

number_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(allow_nan=True, allow_infinity=True).map(lambda x: f"{x:g}"),
    st.integers(min_value=-10**30, max_value=10**30).map(str),
    st.sampled_from(["nan", "NaN", "-nan", "inf", "-Infinity", "1e309", "0x10", "1,5",
                     "", " ", "1_000", "+7", "٣"]),
    st.text(max_size=8),
)


def _parse(cmd: str, argv: list[str]) -> tuple[Any, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            return _PARSERS[cmd].parse_args(argv), ""
        except SystemExit as exc:
            assert exc.code == 2
    return None, err.getvalue()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=st.sampled_from(NUMERIC_OPTIONS), text=number_text)
def test_any_text_for_a_numeric_option_is_in_range_or_one_line(
        case: tuple[str, str, float, float], text: str) -> None:
    cmd, opt, lo, hi = case
    positional = ["x.log"] if cmd == "replay" else []
    args, err = _parse(cmd, [cmd, *positional, f"{opt}={text}"])
    if args is not None:
        value = getattr(args, opt.lstrip("-").replace("-", "_"))
        assert math.isfinite(value) and lo <= value <= hi
    else:
        assert err.count("\n") == 1 and f"rig {cmd}: argument {opt}" in err, err


@settings(max_examples=200, deadline=None)
@given(text=number_text)
@example(text="--")      # Python 3.11's argparse drops a lone '--' value unconverted
def test_any_text_for_the_seed_is_a_valid_seed_or_one_line(text: str) -> None:
    args, err = _parse("sim", ["sim", f"--seed={text}"])
    if args is not None:
        np.random.default_rng(args.seed)          # numpy accepts it
        assert 0 <= args.seed < 2**63
    else:
        assert err.count("\n") == 1 and "--seed" in err


# ---------------------------------------------------------------------------- strict JSON

def _strict_loads(text: str) -> Any:
    def refuse(name: str) -> Any:
        raise AssertionError(f"{name} in the JSON output")
    return json.loads(text, parse_constant=refuse)


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.text(max_size=5),
              st.floats(allow_nan=True, allow_infinity=True),
              st.floats(allow_nan=True, allow_infinity=True, width=32).map(np.float32),
              st.integers(-100, 100).map(np.int64)),
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.lists(inner, max_size=4).map(tuple),
                            st.dictionaries(st.text(max_size=4), inner, max_size=4)),
    max_leaves=20)


def _expected(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _expected(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_expected(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


@settings(max_examples=300, deadline=None)
@given(value=json_values)
def test_strict_json_never_prints_nan_or_infinity(value: Any) -> None:
    text = strict_json.dumps(value)
    assert _strict_loads(text) == _expected(value)     # finite numbers survive exactly


def test_json_commands_print_strict_json(monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    import rig.commands.analyze as analyze_cmd

    real = analyze_cmd.analyze

    def with_non_finite(cfg: Any, w: int) -> Any:
        res = real(cfg, w)
        name = next(iter(res))
        res[name]["lq"]["absorbed_power_ratio"] = math.inf
        res[name]["lqg"]["rattlespace_rms_ratio"] = math.nan
        return res

    monkeypatch.setattr(analyze_cmd, "analyze", with_non_finite)
    assert main(["analyze", "--json"]) == 0
    out = _strict_loads(capsys.readouterr().out)
    name = next(iter(out["models"]))
    assert out["models"][name]["lq"]["absorbed_power_ratio"] is None
    assert out["models"][name]["lqg"]["rattlespace_rms_ratio"] is None
    assert main(["sim", "--road", "bump", "--duration", "0.5", "--controller", "passive",
                 "--json"]) == 0
    _strict_loads(capsys.readouterr().out)


def test_replay_json_is_strict(files: dict[str, Path], design_file: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(files["ok_log"]), "--design", str(design_file),
                 "--json"]) == 0
    out = _strict_loads(capsys.readouterr().out)
    assert out["max_abs_command_diff"] is None          # nothing to compare on a log
