"""Identification (issue 14): the excitation, its run and recording, `rig identify`
(recovery, intervals, JSON, --out, refusals) and its HTML report in headless Chromium."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import matplotlib.image as mpimg
import numpy as np
import pytest
from scipy import signal

from controller.config import (
    ConfigError,
    default_config,
    layer_scales,
    load_config,
    parse_config,
)
from controller.design import design_bank
from controller.excitation import chirp_frequency_hz, excitation_force
from controller.identify import (
    IdentificationRefusedError,
    RunData,
    identify,
)
from hil.sim.excitation_run import simulate_excitation
from hil.sim.roads import check_road, make_road
from rig.cli import main as rig_main
from rig.report.identify import IDENTIFY_FIGURES, MEASURED_COLOUR, MODEL_COLOUR
from rig.report.series import load_series
from tests.support.browser import chromium, chromium_run
from tests.support.identify_run import ARM_S, IDENT_CFG, record_identification_run, true_values

pytestmark = pytest.mark.timeout(300)


# ---------------------------------------------------------------------------- excitation


def test_excitation_is_seeded_bounded_tapered_and_spans_the_band() -> None:
    cfg = IDENT_CFG
    f = excitation_force(cfg)
    ex = cfg.excitation
    assert f.shape == (round(ex.duration_s * cfg.design.sample_rate_hz),)
    assert np.array_equal(f, excitation_force(cfg))                       # deterministic
    other = excitation_force(cfg.replace(excitation={"seed": 2}))
    assert not np.array_equal(f, other)                                   # the seed counts
    assert np.max(np.abs(f)) <= ex.chirp_amplitude_n + ex.prbs_amplitude_n + 1e-9
    assert f[0] == 0.0 and abs(f[-1]) < 1.0                               # faded in / out
    t = np.array([0.0, ex.duration_s])
    assert np.allclose(chirp_frequency_hz(cfg, t), [ex.chirp_start_hz, ex.chirp_stop_hz])
    # power in every octave from 0.5 to 25 Hz (the chirp sweeps it; PRBS is flat)
    fr, p = signal.welch(f, fs=cfg.design.sample_rate_hz, nperseg=4096)
    for lo in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0):
        band = (fr >= lo) & (fr < 2 * lo)
        assert np.mean(p[band]) > 1e-3 * np.max(p), lo


@pytest.mark.parametrize(("section", "key", "value", "why"), [
    ("excitation", "chirp_stop_hz", 0.4, "chirp_start_hz"),
    ("excitation", "taper_s", 10.0, "duration_s"),
    ("excitation", "duration_s", 1.0, "[2.0, 3600.0]"),
])
def test_excitation_config_errors_name_the_key(section: str, key: str, value: float,
                                               why: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({section: {key: value}})
    assert f"{section}.{key}" in str(err.value) and why in str(err.value)


@pytest.mark.parametrize(("changes", "key", "why"), [
    ({"excitation": {"chirp_amplitude_n": 7950.0}}, "chirp_amplitude_n", "force_limit_n"),
    ({"excitation": {"travel_limit_m": 0.09}}, "travel_limit_m", "rattlespace_travel_m"),
    ({"excitation": {"chirp_stop_hz": 300.0}, "design": {"sample_rate_hz": 500.0}},
     "chirp_stop_hz", "Nyquist"),
])
def test_an_excitation_that_does_not_fit_the_rig_is_refused_when_built(
        changes: dict[str, Any], key: str, why: str) -> None:
    """Checked when an excitation is built, not for every configuration: a configuration
    made for other runs (short travel, a low rate) stays valid."""
    cfg = parse_config(changes)
    with pytest.raises(ConfigError) as err:
        excitation_force(cfg)
    assert f"excitation.{key}" in str(err.value) and why in str(err.value)


def test_flat_road_holds_the_shaker_at_rest() -> None:
    assert check_road("flat") == "flat"
    road = make_road("flat", 10.0, 2.0, 1e-3)
    assert not road.height_m.any() and not road.velocity_mps.any()


# ---------------------------------------------------------------------------- the run


def test_recording_marks_the_excitation_played_through_the_loop(identification_run: Path
                                                                 ) -> None:
    s = load_series(identification_run)
    ex = [e for e in s.events if e["kind"] == "excitation"]
    assert [e["detail"]["phase"] for e in ex] == ["start", "end"]
    start, end = ex[0]["tick"], ex[1]["tick"]
    n = ex[0]["detail"]["samples"]
    assert end - start == n == round(IDENT_CFG.excitation.duration_s * 1000)
    enabled = s.signals["valve_enable"] > 0
    assert enabled[(s.tick >= start) & (s.tick < end)].all()
    assert not enabled[s.tick >= end].any()                  # disarmed at its end
    assert not enabled[s.tick < start].any()
    # the applied force reference is the excitation, sample for sample
    ref = s.signals["force_ref_n"][(s.tick >= start) & (s.tick < end)]
    assert np.array_equal(ref, excitation_force(IDENT_CFG))


def test_travel_limit_stops_the_excitation_safe(design_path: Path, tmp_path: Path) -> None:
    cfg = IDENT_CFG.replace(excitation={"travel_limit_m": 0.003})
    path = record_identification_run(tmp_path / "limit.mcap", design_path.read_bytes(), cfg,
                                     seconds=ARM_S + 3.0)
    s = load_series(path)
    ex = [e for e in s.events if e["kind"] == "excitation"]
    assert ex[-1]["detail"]["phase"] == "aborted"
    assert "travel limit" in ex[-1]["detail"]["reason"]
    stop = ex[-1]["tick"]
    assert not (s.signals["valve_enable"][s.tick > stop] > 0).any()
    assert np.max(np.abs(s.signals["rattlespace_m"][s.tick <= stop])) < 0.003 + 0.003


# ---------------------------------------------------------------------------- identify


@pytest.fixture(scope="module")
def identified(identification_run: Path, tmp_path_factory: pytest.TempPathFactory
               ) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("identified")
    fitted, report = out / "fitted.toml", out / "identify.html"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = rig_main(["identify", str(identification_run), "--json", "--out", str(fitted),
                         "--report", str(report)])
    assert code == 0
    return {"json": json.loads(buf.getvalue()), "fitted": fitted, "report": report}


def test_recovers_the_emulated_rig_within_tolerance(identified: dict[str, Any]) -> None:
    est, ci = identified["json"]["estimates"], identified["json"]["ci95"]
    tol = {"vehicle.sprung_mass_kg": 0.01, "vehicle.suspension_stiffness_n_per_m": 0.01,
           "vehicle.suspension_damping_ns_per_m": 0.01, "vehicle.unsprung_mass_kg": 0.03,
           "tire.stiffness_coefficient": 0.03}
    for key, truth in true_values().items():
        assert abs(est[key] / truth - 1.0) < tol[key], (key, est[key], truth)
        lo, hi = ci[key]
        assert lo <= truth <= hi, (key, lo, truth, hi)
    # sensor offsets: the configured (zero) offsets lie in their intervals
    for key in ("sensors.load_cell_offset_n", "sensors.accel_bias_mps2"):
        lo, hi = ci[key]
        assert lo <= 0.0 <= hi


def test_json_keys_are_config_keys_and_intervals_bracket(identified: dict[str, Any]) -> None:
    doc = identified["json"]
    assert set(doc) == {"estimates", "ci95", "fit", "recording"}
    assert doc["recording"] == {"complete": True, "stopped_at": None,
                                "excitation_ended": True}
    assert set(doc["ci95"]) == set(doc["estimates"])
    cfg = default_config()
    for key, value in doc["estimates"].items():
        section, name = key.split(".")
        assert hasattr(getattr(cfg, section), name), key
        lo, hi = doc["ci95"][key]
        assert lo <= value <= hi and math.isfinite(lo) and math.isfinite(hi)
    # what was not identified is said, with a reason, and is not among the estimates
    nid = doc["fit"]["not_identified"]
    assert "tire.stiffness_exponent" in nid and "not identified" in nid[
        "tire.stiffness_exponent"]
    assert not set(nid) & set(doc["estimates"])
    # the frequency-domain cross-check agrees on M and C
    rel = doc["fit"]["frequency_domain"]["relative_difference"]
    assert abs(rel["vehicle.sprung_mass_kg"]) < 0.03
    assert abs(rel["vehicle.suspension_damping_ns_per_m"]) < 0.05


def test_fitted_config_loads_and_designs(identified: dict[str, Any]) -> None:
    cfg = load_config(identified["fitted"])
    est = identified["json"]["estimates"]
    assert cfg.vehicle.sprung_mass_kg == pytest.approx(est["vehicle.sprung_mass_kg"])
    assert cfg.tire.stiffness_coefficient == pytest.approx(est["tire.stiffness_coefficient"])
    # the emulated rig stays the recorded one (its scales re-expressed about the fit)
    truth = true_values()
    assert cfg.vehicle.sprung_mass_kg * cfg.emulator.sprung_mass_scale == pytest.approx(
        truth["vehicle.sprung_mass_kg"])
    design = design_bank(cfg)       # the tire models once per layer, and the airborne one
    assert design.n_models == (len(cfg.design.linearisation_deflections_m)
                               * len(cfg.design.tire_damping_scales)
                               * len(layer_scales(cfg)) + 1)


def test_rig_design_takes_the_fitted_config(identified: dict[str, Any], tmp_path: Path
                                            ) -> None:
    out = tmp_path / "fitted.npz"
    assert rig_main(["design", "--config", str(identified["fitted"]), "--out", str(out)]) == 0
    assert out.stat().st_size > 0


# ---------------------------------------------------------------------------- refusals


def _offline(cfg: Any = IDENT_CFG, **kw: Any) -> RunData:
    ch = simulate_excitation(cfg, seed=3, **kw)
    excite = ch["excitation"] > 0
    rest = np.zeros_like(excite)
    rest[:round(cfg.excitation.rest_s * 1000)] = True
    return RunData(cfg.sample_time_s, ch["rattlespace_m"], ch["sprung_accel_mps2"],
                   ch["force_meas_n"], ch["force_ref_n"], ch["spool_cmd"], excite, rest)


def _refusal(data: RunData, cfg: Any = IDENT_CFG) -> str:
    with pytest.raises(IdentificationRefusedError) as err:
        identify(data, cfg)
    msg = str(err.value)
    assert "\n" not in msg
    return msg


def test_refuses_without_excitation_too_short_saturated_or_off_the_ground() -> None:
    data = _offline()
    none = RunData(**{**data.__dict__, "excite": np.zeros_like(data.excite)})
    assert _refusal(none).startswith("no excitation segment")
    short = data.excite.copy()
    short[np.flatnonzero(short)[3000:]] = False
    assert _refusal(RunData(**{**data.__dict__, "excite": short})).startswith(
        "excitation too short")
    spool = data.spool_cmd.copy()
    idx = np.flatnonzero(data.excite)
    spool[idx[1000:1200]] = 1.0
    assert "saturated: the spool command" in _refusal(
        RunData(**{**data.__dict__, "spool_cmd": spool}))
    # a light wheel on a soft tire driven hard leaves the ground
    hard = IDENT_CFG.replace(excitation={"chirp_amplitude_n": 3000.0,
                                         "prbs_amplitude_n": 1500.0,
                                         "chirp_corner_hz": 8.0})
    assert _refusal(_offline(hard), hard).startswith("wheel off the ground")


def test_cli_refusals_are_one_line_exit_2(design_path: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    from hil.stepped_run import record_emulated_run

    plain = record_emulated_run(tmp_path / "plain.mcap", 1.0, cfg=IDENT_CFG,
                                design_bytes=design_path.read_bytes(), road="flat")
    assert rig_main(["identify", str(plain)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no excitation segment" in err
    assert "Traceback" not in err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap")
    assert rig_main(["identify", str(junk)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


# ---------------------------------------------------------------------------- report


def _pixels_near(img: np.ndarray, colour: str, tol: float = 8.0) -> int:
    rgb = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)], dtype=float)
    px = img[..., :3].astype(float)
    if px.max() <= 1.0:
        px = px * 255.0
    return int(np.sum(np.all(np.abs(px - rgb) <= tol, axis=-1)))


def test_report_renders_in_headless_chromium(identified: dict[str, Any],
                                             tmp_path: Path) -> None:
    browser = chromium()
    page = identified["report"]
    dom = chromium_run(browser, page, "--dump-dom")
    n = len(IDENTIFY_FIGURES)
    assert f'data-images-loaded="{n}/{n}"' in dom, dom[:500]
    assert "<h1>Identification of" in dom and "vehicle.sprung_mass_kg" in dom
    # a page whose Bode plot is gone reports it (the check can fail)
    broken = tmp_path / "broken.html"
    broken.write_text(page.read_text().replace("src='data:image/png;base64,", "src='x", 1))
    dom = chromium_run(browser, broken, "--dump-dom")
    assert f'data-images-loaded="{n - 1}/{n}"' in dom
    shot = tmp_path / "identify.png"
    chromium_run(browser, page, "--window-size=1100,3000", f"--screenshot={shot}")
    img = np.asarray(mpimg.imread(shot))
    assert float(np.std(img[..., :3])) > 0.05
    # measured and model curves are both drawn
    assert _pixels_near(img, MEASURED_COLOUR) > 2000
    assert _pixels_near(img, MODEL_COLOUR) > 1000


# ---------------------------------------------------------------------------- services


@pytest.mark.timeout(300)
def test_unattended_excite_run_arms_after_rest_and_stops_after_it(design_path: Path,
                                                                  tmp_path: Path) -> None:
    """`rig run --excite` as the service runs it (here against the emulated rig in its
    own process with the road 'flat', as `rig hil --excite`): rest, arm, excitation,
    disarm, stop by itself.  In lockstep, so the run is the same whatever the machine's
    load (in real time a busy host once stretched the loop's ticks enough for the
    excitation to cross its travel limit at sample 1807 of 2000)."""
    from hil.harness import RigHarness, RigProcessOptions
    from rig.service.runner import ServiceOptions

    cfg = IDENT_CFG.replace(excitation={"duration_s": 2.0, "rest_s": 0.5},
                            safety={"stale_ticks": 1000, "overrun_streak": 100000,
                                    "rig_status_stale_ticks": 100000})
    record = tmp_path / "run.mcap"
    opts = ServiceOptions(design_path=str(design_path), telemetry=False, realtime=None,
                          install_signal_handlers=False, record=str(record), arm=True,
                          excite=True)
    rig_opts = RigProcessOptions(road="flat", road_s=10.0, watchdog_s=10.0, realtime=None,
                                 trace_ticks=20_000, lockstep=True)
    h = RigHarness(cfg, opts, rig_opts, max_speedup=0.0)
    try:
        res = h.run()
    finally:
        h.close()
    s = load_series(record)
    ex = [e for e in s.events if e["kind"] == "excitation"]
    assert h.service.exit_reason == "excitation ended", ex
    assert res.ticks_run < 6000          # stopped by itself, 0.5 s after the excitation
    assert [e["detail"]["phase"] for e in ex] == ["start", "end"]
    # after the rest, counted in loop ticks as the service counts it (the recorded times
    # carry the wake-up lateness of the first tick)
    assert ex[0]["tick"] - s.tick[0] >= round(0.5 * cfg.design.sample_rate_hz)
    # the rig's true body acceleration in the passive rest: still (the road is at rest;
    # on the default rough course it is metres per second squared)
    assert np.max(np.abs(res.trace["accel_mps2"][:400])) < 1e-6


def test_demo_excite_needs_room_for_rest_and_excitation(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    assert rig_main(["demo", "--excite", "--duration", "5", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--excite needs --duration >= 22.5 s" in err


def test_hil_excite_holds_the_road_at_rest(capsys: pytest.CaptureFixture[str]) -> None:
    assert rig_main(["hil", "--excite", "--interface", "virtual", "--channel",
                     "test-identify-hil", "--duration", "0.05"]) == 0
    assert "rig hil:" in capsys.readouterr().out


def test_replay_reproduces_the_identification_run(identification_run: Path) -> None:
    """Replay rebuilds the excitation from the recorded configuration: every sent frame
    (valve commands carrying the excitation's force reference) is reproduced."""
    from rig.replay.driver import replay_recording

    res = replay_recording(identification_run, reader_process=False)
    assert res.tx_frames_compared > 8000
    assert res.tx_frames_mismatched == 0, res.first_mismatch
