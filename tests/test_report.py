"""Run report (rig/report/): plots, phases, metrics and the force-tracking analysis against
independent computations, events from the fault codes' descriptions, the open-loop
comparison page of a replay, bad files, and the page as headless Chromium renders it.

The module's runs use the configured rig with a one-layer bank
(:func:`controller.config.one_layer`, and :func:`design_path` its design): the fixture
run's models plot shows every model of the bank in its own colour, and the page of a
one-layer bank has no layers to show, whatever layers the built-in defaults have; a
layered bank's page has its own test."""

from __future__ import annotations

import itertools
import math
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import cantools
import numpy as np
import pytest
from matplotlib import image as mpimg
from scipy import signal

from controller.actuator import servo_model
from controller.artifact import save_design
from controller.config import RigConfig, default_config, one_layer
from controller.design import design_bank
from controller.runtime.kernels import StepFlag
from controller.wheel_hop import passive_wheel_hop_hz, tire_stiffness_scale
from hil.stepped_run import record_emulated_run
from rig.cli import main as rig_main
from rig.recording.recorder import read_run
from rig.replay import ScanResult, replay_recording
from rig.report import (
    Phase,
    RunSeries,
    event_rows,
    force_tracking,
    load_series,
    phase_metrics,
    run_metrics,
    write_report,
)
from rig.report.page import _summary_table
from rig.report.plots import (
    DPI,
    MAX_PLOT_POINTS,
    MODEL_COLOURS,
    PHASE_ALPHA,
    PHASE_COLOURS,
    WIDTH_IN,
    envelope,
)
from rig.wire.protocol import VALVE_COMMAND_ID, FaultCode
from tests.support.browser import chromium, chromium_run
from tests.support.mcap_reference import items_of_run, reference_items

pytestmark = pytest.mark.timeout(300)
CFG = one_layer(default_config())
DBC: Any = cantools.database.load_file(str(Path(__file__).parents[1] / "rig" / "wire" / "rig.dbc"))
PLOTS = ["summary.png", "rattlespace.png", "acceleration.png", "force.png",
         "force_tracking.png", "models.png", "sprung_mass.png", "lifecycle.png", "timing.png"]
#: the fixture run: passive, active, an overrun-streak fault, reset, active again
ARM_S, LATE_TICK, RESET_TICK, REARM_TICK, SECONDS = 0.4, 2000, 2600, 2700, 4.0


@pytest.fixture(scope="module")
def work() -> Any:
    with tempfile.TemporaryDirectory(prefix="test-report-") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def design_path(work: Path) -> Path:
    """The design of :data:`CFG` (one layer) as an artifact file."""
    path = work / "design.npz"
    save_design(design_bank(CFG), path)
    return path


@pytest.fixture(scope="module")
def recording(work: Path, design_path: Path) -> Path:
    return record_emulated_run(work / "run.mcap", SECONDS, cfg=CFG,
                               design_bytes=design_path.read_bytes(),
                               arm_at_s=ARM_S,
                               late_ticks={k: 900_000 for k in range(LATE_TICK, LATE_TICK + 6)},
                               commands={RESET_TICK: ("reset", None),
                                         REARM_TICK: ("arm", None)})


@pytest.fixture(scope="module")
def report(recording: Path, work: Path) -> Path:
    return write_report(recording, work / "report")


def _img_srcs(index: Path) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', index.read_text())


def _rgb(colour: str) -> np.ndarray:
    return np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)], dtype=float)


def _pixels_near(img: np.ndarray, rgb: np.ndarray, tol: float = 6.0) -> int:
    """Pixels of an RGB(A) image (floats 0..1 or ints 0..255) within ``tol`` of ``rgb``."""
    px = img[..., :3].astype(float)
    if px.max() <= 1.0:
        px = px * 255.0
    return int(np.sum(np.all(np.abs(px - rgb) <= tol, axis=-1)))


def _shade(colour: str) -> np.ndarray:
    """A phase colour as shaded on white."""
    return 255.0 * (1 - PHASE_ALPHA) + _rgb(colour) * PHASE_ALPHA


# ---------------------------------------------------------------------------- plots


def test_report_has_every_plot_same_width_and_not_blank(report: Path) -> None:
    assert _img_srcs(report) == PLOTS
    for name in PLOTS:
        img = mpimg.imread(report.parent / name)
        assert img.shape[1] == round(WIDTH_IN * DPI) and img.shape[0] > 150, name
        assert float(np.std(img[..., :3])) > 0.01, name   # something was drawn


def test_each_model_has_its_own_colour_and_legend(report: Path, recording: Path) -> None:
    s = load_series(recording)
    J = len(s.model_names)
    assert J >= 3 and s.model_names[0] != "model 0"      # names from the design
    assert len(set(MODEL_COLOURS[:J])) == J
    assert not {c.lower() for c in MODEL_COLOURS} & {c.lower() for c in PHASE_COLOURS.values()}
    img = mpimg.imread(report.parent / "models.png")
    for j in range(J):
        assert _pixels_near(img, _rgb(MODEL_COLOURS[j])) > 50, (j, s.model_names[j])
    html = report.read_text()
    for name in s.model_names:
        assert name in html
    # the drawing check can fail: a colour nobody uses is not found
    assert _pixels_near(img, _rgb("#00ffff")) == 0


def test_a_layered_bank_shows_the_models_that_ran(work: Path) -> None:
    """A bank layered over sprung mass (docs/design.md §11) runs one layer at a time: the
    models plot and its caption name the models whose filter ran, not every model of the
    design (with 190 models the plot's legend left no room for the axes)."""
    cfg = CFG.replace(design={"sprung_mass_scales": [0.7, 1.0]})
    path = work / "layered-design.npz"
    save_design(design_bank(cfg), path)
    rec = record_emulated_run(work / "layered.mcap", 1.0, cfg=cfg,
                              design_bytes=path.read_bytes(), arm_at_s=0.2)
    # the record carries the running layer's four models (bank indices in "models"):
    # three tire models of layer 0 (0.7 x) or 1 (1.0 x), then the airborne model
    internals = [r.data for r in read_run(rec).records if "models" in r.data]
    assert internals and all(len(r["q"]) == 4 and len(r["x_post"]) == 16 for r in internals)
    assert {tuple(r["models"]) for r in internals} <= {(0, 1, 2, 6), (3, 4, 5, 6)}
    s = load_series(rec)
    J = len(s.model_names)
    ran = [j for j in range(J) if np.any(s.per_model["q"][:, j] > 0)]
    assert J == 7 and 0 < len(ran) < J
    for r, row in zip(internals[-5:], range(len(s.tick) - 5, len(s.tick)), strict=True):
        assert s.per_model["q"][row, r["models"]].tolist() == r["q"]   # spread back
    assert all("_M1" in s.model_names[j] or s.model_names[j] == "airborne" for j in ran)
    # the layer it ran, per tick, from the first column's model index and the config
    v = CFG.vehicle
    mkc = [v.sprung_mass_kg, v.suspension_stiffness_n_per_m, v.suspension_damping_ns_per_m]
    assert np.array_equal(s.layer_mkc, np.tile(mkc, (len(s.tick), 1)))
    html = write_report(rec, work / "layered-report").read_text()
    assert (f"The bank ran 1 of its layers (the red line is the running layer's mass; "
            f"each layer is the design for one sprung mass, spring rate and damping): "
            f"{mkc[0]:.0f} kg, {mkc[1]:.0f} N/m, {mkc[2]:.0f} N s/m for ") in html
    assert f"The {len(ran)} of the design's {J} linear models whose filter ran" in html
    caption = html[html.index("whose filter ran"):html.index("q is each model")]
    for j in range(J):      # the mean firing weights while active: the models that ran
        assert (f"{s.model_names[j]} " in caption) == (j in ran), s.model_names[j]


def test_every_time_plot_shades_the_phases_alike(report: Path) -> None:
    for name in ("rattlespace.png", "acceleration.png", "force.png", "models.png",
                 "sprung_mass.png", "lifecycle.png", "timing.png"):
        img = mpimg.imread(report.parent / name)
        for phase in Phase:
            assert _pixels_near(img, _shade(PHASE_COLOURS[phase]), tol=3) > 200, (name, phase)


def test_sprung_mass_estimate_is_a_row_and_a_plot(report: Path, recording: Path) -> None:
    """The controller's mass estimate of every tick is read back; the table shows the
    last one of each phase; the page has the plot."""
    s = load_series(recording)
    m = s.sprung_mass_est_kg
    assert m.size == s.t_s.size and np.all(np.isfinite(m))
    active = s.phase == Phase.ACTIVE
    assert phase_metrics(s)["active"]["sprung_mass_est_kg"] == m[active][-1]
    html = report.read_text()
    assert "sprung-mass estimate at the end of the phase" in html
    assert "sprung_mass.png" in html
    # a one-layer bank has no layers to show
    assert np.isnan(s.layer_mkc).all() and "The bank ran" not in html
    # the spring rate and damping fitted beside it: recorded every tick, last of a phase
    for key, label in (("spring_rate_est_n_per_m", "spring-rate estimate"),
                       ("damping_est_ns_per_m", "damping estimate")):
        x = getattr(s, key)
        assert x.size == s.t_s.size and np.all(np.isfinite(x) & (x > 0.0)), key
        assert phase_metrics(s)["active"][key] == x[active][-1]
        assert f"{label} at the end of the phase" in html
    # the runtime's tire estimate: in every record, but none yet (its passive stretches,
    # 0.4 s and the fault's 0.7 s, are short of the 8 s the estimate needs); rows shown
    internals = [r.data for r in read_run(recording).records if "models" in r.data]
    assert len(internals) == s.t_s.size
    for key, row, label in (
            ("wheel_hop_hz", "wheel_hop_est_hz",
             "passive wheel-hop frequency estimate at the end of the phase"),
            ("tire_stiffness_est", "tire_stiffness_est",
             "tire-stiffness estimate at the end of the phase")):
        assert all(key in r and r[key] is None for r in internals), key
        x = getattr(s, key)
        assert x.size == s.t_s.size and np.isnan(x).all(), key
        assert math.isnan(phase_metrics(s)["passive"][row]), key
        assert label in html


def test_long_series_envelope_keeps_every_extreme() -> None:
    rng = np.random.default_rng(5)
    n = 3 * MAX_PLOT_POINTS + 7
    t = np.zeros(n)
    t[:] = np.arange(n) * 1e-3
    y = rng.standard_normal(n)
    y[12345] = 50.0
    tt, lo, hi = envelope(t, y)
    assert tt.size == lo.size == hi.size <= MAX_PLOT_POINTS
    b = n // tt.size
    for k in (0, 12345 // b, tt.size - 1):   # reference: min / max of the bucket
        assert hi[k] == y[k * b:(k + 1) * b].max() and lo[k] == y[k * b:(k + 1) * b].min()
    assert hi.max() == 50.0
    short = np.zeros(10)
    short[:] = range(10)
    assert envelope(short, short)[1] is short


# ---------------------------------------------------------------------------- series


def test_phases_follow_the_valve_and_the_lifecycle(recording: Path) -> None:
    s = load_series(recording)
    run = read_run(recording)            # checked against the mcap library's reader below
    enable = np.array([bool(r.data["valve_enable"]) for r in run.records])
    fault = np.array([r.data["lifecycle"] == "FAULT" for r in run.records])
    assert np.array_equal(s.phase == Phase.ACTIVE, enable)
    assert np.array_equal(s.phase == Phase.FAULT, fault & ~enable)
    assert {Phase(p) for p in s.phase} == set(Phase)
    segs = s.segments
    assert [g.phase for g in segs] == [Phase.PASSIVE, Phase.ACTIVE, Phase.FAULT,
                                       Phase.PASSIVE, Phase.ACTIVE]
    assert segs[0].start == 0 and segs[-1].stop == s.tick.size
    assert all(a.stop == b.start for a, b in itertools.pairwise(segs))
    total = sum(s.time_in(p) for p in Phase)
    assert total == pytest.approx(s.t_s[-1] + s.dt_s)


def test_applied_force_reference_is_what_the_valve_command_carried(recording: Path) -> None:
    """force_ref_n is recorded in every state; the ValveCommand frames on /can/tx (decoded
    by cantools from the DBC) carry it only while enabled: the report plots those."""
    s = load_series(recording)
    run = read_run(recording)
    sent: dict[int, dict[str, Any]] = {}
    for f in run.frames:
        if not f.is_rx and f.arbitration_id == VALVE_COMMAND_ID:
            sent[f.tick] = DBC.decode_message(VALVE_COMMAND_ID, f.data, decode_choices=False)
    ticks = [int(k) for k in s.tick if int(k) in sent]
    assert len(ticks) > 0.99 * s.tick.size
    idx = np.searchsorted(s.tick, ticks)
    enable = np.array([sent[k]["Enable"] for k in ticks])
    fref = np.array([sent[k]["ForceReference"] for k in ticks])
    assert np.array_equal(enable, s.signals["valve_enable"][idx].astype(int))
    off = enable == 0
    assert off.any() and np.all(fref[off] == 0.0)
    assert np.abs(s.signals["force_ref_n"][idx][off]).max() > 100.0   # computed, not sent
    assert np.all(s.force_ref_applied_n[idx][off] == 0.0)
    lim = CFG.force_loop.force_limit_n
    inside = ~off & (np.abs(fref) < lim)
    assert inside.sum() > 1000
    assert np.abs(s.force_ref_applied_n[idx][inside] - fref[inside]).max() <= 0.25 + 1e-9


def test_metrics_against_independent_computations(recording: Path) -> None:
    s = load_series(recording)
    m = run_metrics(s)
    run = read_run(recording)
    # read_run and the report share the scanner: the mcap library's reader is the
    # independent reference for what the file holds
    assert items_of_run(run) == reference_items([recording], validate=False)
    rs = np.array([r.data["rattlespace_m"] for r in run.records])
    acc = np.array([r.data["sprung_accel_mps2"] for r in run.records])
    active = np.array([bool(r.data["valve_enable"]) for r in run.records])
    assert m["ticks"] == rs.size
    assert m["rattlespace_rms_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(rs ** 2)), rel=1e-12)
    assert m["rattlespace_peak_mm"] == pytest.approx(1e3 * np.abs(rs).max(), rel=1e-12)
    # absorbed power proxy: F(s) = 12 s / (s^2 + 30.02 s + 901.3) by scipy's lsim
    # (another discretisation than the report's bilinear filter)
    t = np.arange(acc.size) * 1e-3
    _, y, _ = signal.lsim(([12.0, 0.0], [1.0, 30.02, 901.3]), acc, t)
    assert m["absorbed_power_proxy"] == pytest.approx(np.mean(y ** 2), rel=0.03)
    assert m["faults"] == 1 and m["recording"] == "complete"
    assert m["time_active_s"] == pytest.approx(active.sum() * 1e-3)
    ph = phase_metrics(s)
    for name, mask in (("passive", ~active), ("active", active)):
        assert ph[name]["time_s"] == pytest.approx(mask.sum() * 1e-3)
        assert ph[name]["rattlespace_rms_mm"] == pytest.approx(
            1e3 * np.sqrt(np.mean(rs[mask] ** 2)), rel=1e-12)
        assert ph[name]["absorbed_power_proxy"] == pytest.approx(np.mean(y[mask] ** 2),
                                                                  rel=0.05)
    fref = np.array([r.data["force_ref_n"] for r in run.records])
    fmeas = np.array([r.data["force_meas_n"] for r in run.records])
    err = np.clip(fref, -CFG.force_loop.force_limit_n, CFG.force_loop.force_limit_n) - fmeas
    assert ph["active"]["tracking_error_rms_n"] == pytest.approx(
        np.sqrt(np.mean(err[active] ** 2)), rel=1e-12)
    assert math.isnan(ph["passive"]["tracking_error_rms_n"])
    assert ph["passive"]["force_ref_applied_rms_n"] == 0.0
    flags = np.array([r.data["flags"] for r in run.records])
    nf = (flags & int(StepFlag.NO_RULE_FIRED)) != 0
    assert ph["active"]["no_rule_fired_pct"] == pytest.approx(100 * nf[active].mean())


# ---------------------------------------------------------------------------- tracking


def _synthetic(ref: np.ndarray, meas: np.ndarray, rattlespace: np.ndarray,
               flags: np.ndarray | None = None, dt: float = 1e-3,
               cfg: RigConfig = CFG) -> RunSeries:
    """A RunSeries made of arrays, valve on throughout."""
    n = ref.size
    nan = np.full(n, np.nan)
    sig = {"rattlespace_m": rattlespace, "sprung_accel_mps2": np.zeros(n),
           "force_meas_n": meas, "force_ref_n": ref, "spool_cmd": nan,
           "valve_enable": np.ones(n)}
    timing = {k: nan for k in ("wake_late_s", "compute_s", "period_s", "overrun",
                               "overruns_total")}
    return RunSeries(Path("synthetic.mcap"), ScanResult(), np.arange(n, dtype=np.int64),
                     np.arange(n) * dt, 0, sig, ["ACTIVE"] * n, [None] * n,
                     {k: np.zeros((n, 0)) for k in ("q", "firing_weight", "probability",
                                                    "u_model")},
                     timing, [], [], cfg, "",
                     flags if flags is not None else np.zeros(n, np.int64))


def test_tracking_error_along_the_rattlespace_rate_has_the_oil_column_slope() -> None:
    """Without the flow feedforward: error = -k_h/(kp kq) * d/dt rattlespace (a 2 Hz
    sine) + a 150 Hz tone: the analysis finds the configuration's slope, explains ~all of
    the low band and splits the power."""
    no_ff = CFG.replace(force_loop={"flow_feedforward_gain": 0.0})
    sm = servo_model(no_ff)
    k = sm.hydraulic_stiffness_n_per_m / (sm.kp_per_n * sm.flow_gain_n_per_s)
    t = np.arange(8192) * 1e-3
    rs = 0.02 * np.sin(2 * np.pi * 2.0 * t)
    rate = 0.02 * 2 * np.pi * 2.0 * np.cos(2 * np.pi * 2.0 * t)
    tone = 300.0 * np.sin(2 * np.pi * 150.0 * t)
    ft = force_tracking(_synthetic(-k * rate + tone, np.zeros_like(t), rs, cfg=no_ff))
    assert ft.ok
    assert ft.residual_slope_ns_per_m == pytest.approx(k)
    assert ft.corner_hz == pytest.approx(sm.kp_per_n * sm.flow_gain_n_per_s / (2 * np.pi))
    assert ft.oil_column_ns_per_m == pytest.approx(k)
    assert ft.fitted_slope_ns_per_m == pytest.approx(k, rel=0.02)
    assert ft.explained_below > 0.99
    assert ft.error_rms_below_n == pytest.approx(k * 0.02 * 2 * np.pi * 2.0 / np.sqrt(2),
                                                 rel=0.03)
    assert ft.error_rms_above_n == pytest.approx(300.0 / np.sqrt(2), rel=0.03)
    assert ft.error_rms_n == pytest.approx(np.hypot(ft.error_rms_below_n,
                                                    ft.error_rms_above_n), rel=0.02)
    # the check can fail: an error that does not follow the rate is not explained by it
    other = force_tracking(_synthetic(k * 0.1 * np.sin(2 * np.pi * 3.0 * t),
                                      np.zeros_like(t), rs, cfg=no_ff))
    assert other.explained_below < 0.1
    # with the feedforward (default g = 1) the configuration predicts no velocity slope
    with_ff = force_tracking(_synthetic(-k * rate + tone, np.zeros_like(t), rs))
    assert with_ff.residual_slope_ns_per_m == 0.0 and with_ff.explained_below < 0.05


def test_tracking_lag_of_a_first_order_loop_is_predicted() -> None:
    """The measured force = the reference through a first-order loop with the
    configuration's corner (independent reference: scipy.signal.lfilter of the
    discretised lag): the predicted lag error below the corner matches the measured."""
    from scipy import signal as sps

    fc = servo_model(CFG).kp_per_n * servo_model(CFG).flow_gain_n_per_s / (2 * np.pi)
    dt = 1e-3
    rng = np.random.default_rng(3)
    ref = sps.sosfiltfilt(sps.butter(4, 15.0, fs=1 / dt, output="sos"),
                          rng.normal(0.0, 3000.0, 16384))
    b, a = sps.bilinear([1.0], [1 / (2 * np.pi * fc), 1.0], fs=1 / dt)
    meas = sps.lfilter(b, a, ref)
    ft = force_tracking(_synthetic(ref, meas, np.zeros_like(ref)))
    assert ft.lag_error_rms_below_n == pytest.approx(ft.error_rms_below_n, rel=0.15)


def test_tracking_splits_the_reference_near_no_rule_fired_ticks() -> None:
    t = np.arange(6000) * 1e-3
    ref = 2000.0 * np.sin(2 * np.pi * 3.0 * t)
    flags = np.zeros(t.size, np.int64)
    flags[3000:3400:7] = int(StepFlag.NO_RULE_FIRED)      # the blend drops to 0 N there
    ref[flags != 0] = 0.0
    ft = force_tracking(_synthetic(ref, np.zeros_like(t), np.zeros_like(t), flags))
    assert ft.no_fire_share == pytest.approx(np.count_nonzero(flags) / t.size)
    assert ft.ref_rms_above_near_no_fire_n > 20 * ft.ref_rms_above_elsewhere_n
    none = force_tracking(_synthetic(2000.0 * np.sin(2 * np.pi * 3.0 * t), np.zeros_like(t),
                                     np.zeros_like(t)))
    assert none.no_fire_share == 0.0 and math.isnan(none.ref_rms_above_near_no_fire_n)


def test_stop_contact_row_counts_time_episodes_and_degradations(work: Path) -> None:
    """The stop-contact rows: time with the LVDT beyond a stop, episodes split by the
    monitor's gap, degradations as STOP_DEGRADED rising edges; per phase and whole run,
    and on the page."""
    n = 3000
    hi = CFG.design.bump_stop_centre_lvdt_m + CFG.vehicle.rattlespace_travel_m
    rs = np.zeros(n)
    rs[100:130] = hi + 0.005              # episode 1: 30 ms on the compression stop
    rs[140:150] = hi + 0.002              # 10 ms later: the same episode (gap 50 ms)
    rs[1000:1020] = -hi - 0.003           # episode 2, rebound stop
    rs[2500:2505] = hi + 0.001            # episode 3
    flags = np.zeros(n, np.int64)
    flags[1000:1800] = int(StepFlag.STOP_DEGRADED)
    flags[2600:2700] = int(StepFlag.STOP_DEGRADED | StepFlag.STOP_CONTACT)
    s = _synthetic(np.zeros(n), np.zeros(n), rs, flags)
    contact_s = (30 + 10 + 20 + 5) * 1e-3
    m = run_metrics(s)
    assert m["stop_contact_s"] == pytest.approx(contact_s)
    assert (m["stop_contact_episodes"], m["stop_degradations"]) == (3, 2)
    ph = phase_metrics(s)
    assert ph["active"]["stop_contact_s"] == pytest.approx(contact_s)
    assert ph["passive"]["stop_contact_episodes"] == 0.0
    page = _summary_table(ph)
    assert "time on the bump stops (LVDT)" in page and "stop-contact degradations" in page


def test_short_active_phase_skips_the_analysis_but_not_the_page(work: Path,
                                                                design_path: Path) -> None:
    rec = record_emulated_run(work / "short.mcap", 0.5, cfg=CFG,
                              design_bytes=design_path.read_bytes(),
                              arm_at_s=0.3)
    s = load_series(rec)
    assert not force_tracking(s).ok
    index = write_report(rec, work / "short-report")
    assert "force_tracking.png" not in _img_srcs(index)
    assert "force.png" in _img_srcs(index)


# ---------------------------------------------------------------------------- events


def test_events_table_uses_the_fault_code_descriptions(recording: Path, report: Path) -> None:
    s = load_series(recording)
    rows = event_rows(s)
    run = read_run(recording)
    assert len(rows) == len(run.events)
    t0 = run.records[0].t_ns
    for row, ev in zip(rows, run.events, strict=True):
        assert row.t_s == pytest.approx((ev.t_ns - t0) * 1e-9)
        assert row.kind == ev.kind and row.tick == ev.tick
    fault = [r for r in rows if r.kind == "fault"]
    assert [r.code for r in fault] == ["OVERRUN_STREAK"]
    assert fault[0].reason == FaultCode.OVERRUN_STREAK.description
    assert fault[0].change == "ACTIVE → FAULT"
    assert fault[0].details.startswith("detail ")            # the loop's own message
    changes = [r.change for r in rows if r.kind == "lifecycle"]
    assert changes[:3] == ["INACTIVE → ACTIVE", "FAULT → INACTIVE", "INACTIVE → ACTIVE"]
    assert [r.code for r in rows if r.kind == "command"] == ["arm", "reset", "arm"]
    html = report.read_text()
    assert FaultCode.OVERRUN_STREAK.description in html
    assert '{"tick"' not in html and "{'tick'" not in html   # no raw JSON dicts
    assert html.count('<tr class="ev-') == len(rows)


def test_page_names_the_recording_channels(report: Path) -> None:
    html = report.read_text()
    paths = set(re.findall(r'data-paths="([^"]+)"', html))
    assert "/rig/signals.rattlespace_m" in paths
    assert any("/controller/internals.firing_weight" in p for p in paths)
    channels = {"/rig/signals", "/rig/timing", "/controller/internals", "/rig/events"}
    for p in " ".join(paths).split():
        assert p.split(".")[0] in channels, p


# ---------------------------------------------------------------------------- CLI, replay


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


# ---------------------------------------------------------------------------- browser


def _screenshot(browser: str, index: Path, png: Path, height: int) -> np.ndarray:
    chromium_run(browser, index, f"--window-size=1100,{height}", f"--screenshot={png}")
    return np.asarray(mpimg.imread(png))


def test_report_renders_in_headless_chromium(report: Path, work: Path) -> None:
    browser = chromium()
    dom = chromium_run(browser, report, "--dump-dom")
    n = len(PLOTS)
    assert f'data-images-loaded="{n}/{n}"' in dom, dom[:500]
    assert "<h1>Run report" in dom
    # the check can fail: a page with a missing plot reports it
    broken = work / "broken"
    shutil.copytree(report.parent, broken)
    (broken / "force.png").unlink()
    dom = chromium_run(browser, broken / "index.html", "--dump-dom")
    assert f'data-images-loaded="{n - 1}/{n}"' in dom


def test_screenshot_shows_summary_events_table_and_model_legend(report: Path,
                                                                work: Path) -> None:
    """What a person sees: the first screen has the passive / active bars and the events
    table with its fault row; the page shows every model's colour (lines and legend of
    the models plot) and the phase shading.  The screenshots stay in the work directory."""
    browser = chromium()
    top = _screenshot(browser, report, work / "screenshot-top.png", 1500)
    assert top.shape[0] == 1500 and float(np.std(top[..., :3])) > 0.05   # not blank
    for phase in (Phase.PASSIVE, Phase.ACTIVE):                           # summary bars
        assert _pixels_near(top, _rgb(PHASE_COLOURS[phase]), tol=4) > 2000, phase
    fault_row = _shade(PHASE_COLOURS[Phase.FAULT])                        # events table
    assert _pixels_near(top, fault_row, tol=3) > 5000
    page = _screenshot(browser, report, work / "screenshot.png", 7000)
    # the same page without the models plot: what that plot adds to the screen
    without = work / "without-models"
    shutil.copytree(report.parent, without)
    (without / "models.png").unlink()
    rest = _screenshot(browser, without / "index.html", work / "screenshot-without.png", 7000)
    J = len(load_series(report.parent.parent / "run.mcap").model_names)
    for j in range(J):
        colour = _rgb(MODEL_COLOURS[j])
        assert _pixels_near(page, colour, tol=8) - _pixels_near(rest, colour, tol=8) > 300, j
    for phase in Phase:
        shade = _shade(PHASE_COLOURS[phase])
        assert _pixels_near(page, shade, tol=3) - _pixels_near(rest, shade, tol=3) > 2000


def _passive_then_active(passive: int = 400, active: int = 600) -> RunSeries:
    """A synthetic run of flat signals: ``passive`` ticks with the valve off, then
    ``active`` ticks ACTIVE (the two phases of :func:`phase_metrics`)."""
    n = passive + active
    s = _synthetic(np.zeros(n), np.zeros(n), np.zeros(n))
    s.lifecycle = ["INACTIVE"] * passive + ["ACTIVE"] * active
    s.signals["valve_enable"][:passive] = 0.0
    return s


def test_comfort_share_row_is_the_phase_mean_and_nan_where_not_recorded() -> None:
    """The travel schedule's row: the mean of the recorded comfort share over each phase;
    a recording without the field (before the schedule) gives NaN, not 0."""
    s = _passive_then_active()
    share = np.concatenate([np.full(400, 0.9), np.linspace(0.0, 1.0, 600)])
    s.comfort_share = share
    ph = phase_metrics(s)
    assert ph["active"]["comfort_share_mean"] == pytest.approx(0.5)
    assert ph["passive"]["comfort_share_mean"] == pytest.approx(0.9)
    assert "travel-schedule comfort share, mean" in _summary_table(ph)
    s.comfort_share = np.zeros(0)
    assert math.isnan(phase_metrics(s)["active"]["comfort_share_mean"])


def test_ride_height_row_is_the_largest_magnitude_and_nan_where_not_recorded() -> None:
    """The ride-height row: the largest |recorded ride height| over each phase (a sag
    toward either stop shows); a recording without the field gives NaN, not 0."""
    s = _passive_then_active()
    s.ride_height_m = np.concatenate([np.full(400, 0.004),
                                      np.linspace(0.01, -0.03, 600)])
    ph = phase_metrics(s)
    assert ph["active"]["ride_height_max_m"] == pytest.approx(0.03)
    assert ph["passive"]["ride_height_max_m"] == pytest.approx(0.004)
    assert "ride height (mean LVDT reading from mid-travel)" in _summary_table(ph)
    s.ride_height_m = np.zeros(0)
    assert math.isnan(phase_metrics(s)["active"]["ride_height_max_m"])


def _row(table: str, label: str) -> list[str]:
    """The passive and active cells of the summary table's row ``label``."""
    m = re.search(re.escape(label) + r'[^<]*</th><td class="num">([^<]*)</td>'
                  r'<td class="num">([^<]*)</td>', table)
    assert m, label
    return [m.group(1), m.group(2)]


TIRE_ROW = "tire-stiffness estimate at the end of the phase [x configured]"
HOP_ROW = "passive wheel-hop frequency estimate at the end of the phase [Hz]"


def test_tire_estimate_rows_are_the_last_of_each_phase_and_nan_where_not_recorded() -> None:
    """The runtime's tire estimate rows: the last recorded value of each phase (none
    yet: NaN; a value, then held while armed), not the offline fit's rows; a recording
    without the fields (before the runtime had them) gives NaN, not 0."""
    s = _passive_then_active()
    hop = np.concatenate([np.full(150, np.nan), np.linspace(9.0, 9.4, 250),
                          np.linspace(9.4, 9.6, 600)])
    s.wheel_hop_hz = hop
    s.tire_stiffness_est = hop / 10.0
    ph = phase_metrics(s)
    assert ph["passive"]["wheel_hop_est_hz"] == hop[399] == 9.4
    assert ph["active"]["wheel_hop_est_hz"] == hop[-1] == 9.6
    assert ph["passive"]["tire_stiffness_est"] == pytest.approx(0.94, rel=1e-12)
    assert ph["active"]["tire_stiffness_est"] == pytest.approx(0.96, rel=1e-12)
    assert math.isnan(ph["passive"]["wheel_hop_hz"])   # the offline fit's row is its own
    table = _summary_table(ph)
    assert _row(table, HOP_ROW) == ["9.4", "9.6"]
    assert _row(table, TIRE_ROW) == ["0.94", "0.96"]
    s.wheel_hop_hz = np.full(1000, np.nan)             # recorded, not yet estimated
    assert math.isnan(phase_metrics(s)["active"]["wheel_hop_est_hz"])
    s.wheel_hop_hz = s.tire_stiffness_est = np.zeros(0)
    ph = phase_metrics(s)
    for name in ("passive", "active"):
        assert math.isnan(ph[name]["wheel_hop_est_hz"])
        assert math.isnan(ph[name]["tire_stiffness_est"])
    assert _row(_summary_table(ph), TIRE_ROW) == ["–", "–"]


def test_runtime_tire_estimate_is_recorded_and_reported(work: Path, design_path: Path
                                                       ) -> None:
    """9 s passive on the road, then armed: the bank's estimate is in every tick record,
    none before 8 s of passive readings, then the wheel hop and the tire it reads
    (about the configured tire: the emulated rig's is) and held while armed; the rows
    show the last of each phase (the passive one, and under the law the held one)."""
    rec = record_emulated_run(work / "tire.mcap", 9.6, cfg=CFG,
                              design_bytes=design_path.read_bytes(), arm_at_s=9.0)
    s = load_series(rec)
    internals = [r.data for r in read_run(rec).records if "models" in r.data]
    assert len(internals) == s.t_s.size
    for key in ("wheel_hop_hz", "tire_stiffness_est"):
        raw = np.array([math.nan if r[key] is None else r[key] for r in internals])
        assert np.array_equal(getattr(s, key), raw, equal_nan=True), key
    hop, tire = s.wheel_hop_hz, s.tire_stiffness_est
    active = s.phase == Phase.ACTIVE
    arm = int(np.argmax(active))                  # one passive phase, then one active
    assert arm > 8000 and active[arm:].all() and not active[:arm].any()
    assert np.isnan(hop[:8000]).all() and np.isnan(tire[:8000]).all()
    assert np.isfinite(hop[~active][-1]) and np.isfinite(hop[active]).all()
    assert np.array_equal(np.isfinite(hop), np.isfinite(tire))
    assert 5.0 < hop[~active][-1] < 20.0 and 0.8 < tire[~active][-1] < 1.2
    assert tire[~active][-1] == pytest.approx(tire_stiffness_scale(hop[~active][-1], CFG),
                                              rel=0.01)
    assert hop[active][-1] == pytest.approx(hop[~active][-1], abs=1e-3)    # held
    ph = phase_metrics(s)
    for name, m in (("passive", ~active), ("active", active)):
        assert ph[name]["wheel_hop_est_hz"] == hop[m][-1]
        assert ph[name]["tire_stiffness_est"] == tire[m][-1]
    table = _summary_table(ph)
    assert _row(table, HOP_ROW)[0] == f"{hop[~active][-1]:.3g}"
    assert _row(table, TIRE_ROW)[1] == f"{tire[active][-1]:.3g}"


def test_a_recording_without_the_tire_estimate_loads_and_reports_nan(
        work: Path, design_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A recording made before the tick record had wheel_hop_hz and tire_stiffness_est
    (the loop's record without them) loads: both columns NaN, the rows NaN, the page
    written."""
    import rig.service.loop as loop_module

    old = tuple(f for f in loop_module.TICK_RECORD_FIELDS
                if f[0] not in ("wheel_hop_hz", "tire_stiffness_est"))
    assert len(old) == len(loop_module.TICK_RECORD_FIELDS) - 2
    monkeypatch.setattr(loop_module, "TICK_RECORD_FIELDS", old)
    rec = record_emulated_run(work / "before-tire.mcap", 0.6, cfg=CFG,
                              design_bytes=design_path.read_bytes(), arm_at_s=0.3)
    internals = [r.data for r in read_run(rec).records if "models" in r.data]
    assert internals and not any("wheel_hop_hz" in r or "tire_stiffness_est" in r
                                 for r in internals)
    assert all("damping_est_ns_per_m" in r for r in internals)
    s = load_series(rec)
    for key in ("wheel_hop_hz", "tire_stiffness_est"):
        x = getattr(s, key)
        assert x.size == s.t_s.size > 0 and np.isnan(x).all(), key
    ph = phase_metrics(s)
    for name in ("passive", "active"):
        assert math.isnan(ph[name]["wheel_hop_est_hz"])
        assert math.isnan(ph[name]["tire_stiffness_est"])
    table = write_report(rec, work / "before-tire-report").read_text()
    assert _row(table, HOP_ROW) == ["–", "–"] and _row(table, TIRE_ROW) == ["–", "–"]


def test_wheel_hop_row_is_each_phases_own_fit_and_nan_on_a_short_phase() -> None:
    """The wheel-hop row: each phase's AR(2) fit on its own LVDT readings (a 9 Hz
    oscillation while passive, 11 Hz while active, a slow body motion under both);
    a phase shorter than the fit's minimum gives NaN, not a number."""
    s = _passive_then_active(passive=8000, active=8000)
    t = np.arange(16000) * 1e-3
    rng = np.random.default_rng(5)
    f = np.where(t < 8.0, 9.0, 11.0)
    s.signals["rattlespace_m"] = (0.002 * np.sin(2 * np.pi * np.cumsum(f) * 1e-3)
                                  + 0.01 * np.sin(2 * np.pi * 1.2 * t)
                                  + 1e-4 * rng.standard_normal(t.size))
    ph = phase_metrics(s)
    assert ph["passive"]["wheel_hop_hz"] == pytest.approx(9.0, abs=0.2)
    assert ph["active"]["wheel_hop_hz"] == pytest.approx(11.0, abs=0.2)
    assert "wheel-hop frequency (AR(2) fit on the LVDT, 5-20 Hz)" in _summary_table(ph)
    assert math.isnan(phase_metrics(_passive_then_active())["active"]["wheel_hop_hz"])


def _wheel_hop_run(f_passive_hz: float) -> RunSeries:
    """10 s passive with a noise-driven oscillation (2 mm RMS) at ``f_passive_hz``
    (damped; damping ratio 0.2) on a slow body motion, then 10 s active at 11 Hz."""
    s = _passive_then_active(passive=10000, active=10000)
    rng = np.random.default_rng(6)
    t = np.arange(20000) * 1e-3
    y = np.zeros(t.size)
    for k, f in enumerate((f_passive_hz / math.sqrt(0.96), 11.0)):
        w0 = 2 * np.pi * f
        part = slice(10000 * k, 10000 * (k + 1))
        _, osc, _ = signal.lsim(([1.0], [1.0, 0.4 * w0, w0 * w0]),
                                rng.standard_normal(10000), t[:10000])
        y[part] = 0.002 * osc / np.std(osc)
    s.signals["rattlespace_m"] = y + 0.01 * np.sin(2 * np.pi * 1.2 * t)
    return s


def test_tire_row_inverts_the_passive_wheel_hop_and_uses_the_estimated_rig() -> None:
    """The tire row: the passive phase's wheel hop through the prediction of
    controller.wheel_hop (the rig of a 0.7 x tire reads about 0.7 x; the fit's bias on
    a lone oscillator is a few %), NaN for the active phase (the law moves the wheel
    hop); with the estimator's spring rate and damping recorded at the end of the active
    phase the same frequency reads as the tire of that rig, not the configured one."""
    cfg = default_config()
    soft = cfg.replace(tire={"stiffness_coefficient": 0.7 * cfg.tire.stiffness_coefficient})
    s = _wheel_hop_run(passive_wheel_hop_hz(soft))
    ph = phase_metrics(s)
    f = ph["passive"]["wheel_hop_hz"]
    assert ph["passive"]["tire_stiffness_scale"] == pytest.approx(
        tire_stiffness_scale(f, cfg), rel=1e-6)
    assert ph["passive"]["tire_stiffness_scale"] == pytest.approx(0.7, abs=0.07)
    assert math.isnan(ph["active"]["tire_stiffness_scale"])
    assert "tire stiffness from the passive wheel hop (x the configured tire)" in \
        _summary_table(ph)
    n = s.signals["rattlespace_m"].size
    v = cfg.vehicle
    s.sprung_mass_est_kg = np.full(n, v.sprung_mass_kg)
    s.spring_rate_est_n_per_m = np.full(n, v.suspension_stiffness_n_per_m)
    s.damping_est_ns_per_m = np.full(n, 1.5 * v.suspension_damping_ns_per_m)
    damped = cfg.replace(vehicle={"suspension_damping_ns_per_m":
                                  1.5 * v.suspension_damping_ns_per_m})
    got = phase_metrics(s)["passive"]["tire_stiffness_scale"]
    assert got == pytest.approx(tire_stiffness_scale(f, damped), rel=1e-6)
    assert got > ph["passive"]["tire_stiffness_scale"] * 1.1
