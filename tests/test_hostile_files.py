"""Hostile bytes in recordings and configuration files (issue 25): every defect is
refused in one line naming what is wrong (tests/support/one_line.py), and a refused
command leaves no partial output behind."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from controller.config import default_config
from tests.support.mcap_edit import rewrite
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
