"""Run report (rig/report.py): plots, metrics against independent computations, the
open-loop comparison page of a replay, bad files, and rendering in headless Chromium."""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib import image as mpimg
from scipy import signal

from bench.replay_bench import record_emulated_run
from controller.artifact import save_design
from controller.config import default_config
from controller.design import design_bank
from rig.cli import main as rig_main
from rig.recording import read_run
from rig.replay import replay_recording
from rig.report import load_series, run_metrics, write_report

pytestmark = pytest.mark.timeout(300)
CFG = default_config()
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run", "--virtual-time-budget=10000"]
PLOTS = ["rattlespace.png", "acceleration.png", "force.png", "models.png", "lifecycle.png",
         "timing.png"]


@pytest.fixture(scope="module")
def work() -> Any:
    with tempfile.TemporaryDirectory(prefix="test-report-") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def recording(work: Path) -> Path:
    p = work / "design.npz"
    save_design(design_bank(CFG), p)
    return record_emulated_run(work / "run.mcap", 0.9, cfg=CFG, design_bytes=p.read_bytes(),
                               late_ticks={k: 900_000 for k in range(600, 606)})


@pytest.fixture(scope="module")
def report(recording: Path, work: Path) -> Path:
    return write_report(recording, work / "report")


def _img_srcs(index: Path) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', index.read_text())


def test_report_has_every_plot_and_they_are_not_blank(report: Path) -> None:
    srcs = _img_srcs(report)
    assert srcs == PLOTS
    for name in srcs:
        img = mpimg.imread(report.parent / name)
        assert img.shape[0] > 100 and img.shape[1] > 400
        assert float(np.std(img[..., :3])) > 0.01, name   # something was drawn


def test_metrics_against_independent_computations(recording: Path) -> None:
    s = load_series(recording)
    m = run_metrics(s)
    run = read_run(recording)                      # the recorder's own reader
    rs = np.array([r.data["rattlespace_m"] for r in run.records])
    acc = np.array([r.data["sprung_accel_mps2"] for r in run.records])
    assert m["ticks"] == rs.size
    assert m["rattlespace_rms_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(rs ** 2)), rel=1e-12)
    assert m["rattlespace_peak_mm"] == pytest.approx(1e3 * np.abs(rs).max(), rel=1e-12)
    # absorbed power proxy: F(s) = 12 s / (s^2 + 30.02 s + 901.3) by scipy's lsim
    # (another discretisation than the report's bilinear filter)
    t = np.arange(acc.size) * 1e-3
    _, y, _ = signal.lsim(([12.0, 0.0], [1.0, 30.02, 901.3]), acc, t)
    assert m["absorbed_power_proxy"] == pytest.approx(np.mean(y ** 2), rel=0.03)
    assert m["faults"] == 1 and m["recording"] == "complete"
    active = np.array([bool(r.data["valve_enable"]) for r in run.records])
    assert m["time_active_s"] == pytest.approx(active.sum() * 1e-3)


def test_replay_report_is_marked_open_loop_and_compares(recording: Path, work: Path) -> None:
    cfg2 = CFG.replace(design={"weight_set": 2})
    p2 = work / "design2.npz"
    save_design(design_bank(cfg2), p2)
    from controller.artifact import load_design

    out = work / "replayed.mcap"
    replay_recording(recording, cfg=cfg2, design=load_design(p2), design_bytes=p2.read_bytes(),
                     out=out)
    index = write_report(out, work / "replayed-report")
    text = index.read_text()
    assert "open loop" in text and str(recording) in text
    assert _img_srcs(index) == [*PLOTS, "comparison.png"]


def test_cli_report_and_bad_files(recording: Path, work: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert rig_main(["report", str(recording), "--out", str(work / "cli")]) == 0
    assert (work / "cli" / "index.html").exists()
    bad = work / "bad.mcap"
    bad.write_bytes(b"PK\x03\x04 this is a zip file")
    assert rig_main(["report", str(bad)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _dump_dom(browser: str, index: Path) -> str:
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile:
        proc = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                               "--dump-dom", index.resolve().as_uri()],
                              capture_output=True, text=True, timeout=90, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_report_renders_in_headless_chromium(report: Path, work: Path) -> None:
    browser = _chromium()
    if browser is None:
        pytest.skip("CHROMIUM NOT INSTALLED: `apt-get install -y chromium` (Debian package "
                    "'chromium') to run the browser rendering test")
    dom = _dump_dom(browser, report)
    n = len(PLOTS)
    assert f'data-images-loaded="{n}/{n}"' in dom, dom[:500]
    assert "<h1>Run report" in dom
    # the check can fail: a page with a missing plot reports it
    broken = work / "broken"
    shutil.copytree(report.parent, broken)
    (broken / "force.png").unlink()
    dom = _dump_dom(browser, broken / "index.html")
    assert f'data-images-loaded="{n - 1}/{n}"' in dom


def test_long_series_envelope_keeps_every_extreme() -> None:
    from rig.report import MAX_PLOT_POINTS, _envelope

    rng = np.random.default_rng(5)
    n = 3 * MAX_PLOT_POINTS + 7
    t = np.zeros(n)
    t[:] = np.arange(n) * 1e-3
    y = rng.standard_normal(n)
    y[12345] = 50.0
    tt, lo, hi = _envelope(t, y)
    assert tt.size == lo.size == hi.size <= MAX_PLOT_POINTS
    b = n // tt.size
    for k in (0, 12345 // b, tt.size - 1):   # reference: min / max of the bucket
        assert hi[k] == y[k * b:(k + 1) * b].max() and lo[k] == y[k * b:(k + 1) * b].min()
    assert hi.max() == 50.0
    short = np.zeros(10)
    short[:] = range(10)
    assert _envelope(short, short)[1] is short
