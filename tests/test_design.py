"""Design bank and artifact: shapes, save/load round trip, mismatch detection, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from controller.actuator import servo_model
from controller.artifact import (
    ARTIFACT_VERSION,
    Design,
    DesignMismatch,
    load_design,
    save_design,
)
from controller.config import (
    RigConfig,
    config_hash,
    default_config,
    design_config_hash,
    layer_params,
    layer_scales,
    layer_tire_scales,
    one_layer,
)
from controller.design import design_bank
from controller.fuzzy import firing_weight
from controller.human_filter import human_filter
from controller.lq import actuated_lq_gain, lq_gain
from controller.plant import LinearModel, model_family
from controller.road_noise import road_velocity_intensity
from rig.cli import main
from tests.support.profiles import write_one_layer_config

CFG = default_config()


def bank_models(cfg: RigConfig) -> list[LinearModel]:
    """The bank's models in its order, from the components: the tire models of
    :func:`model_family` for each layer's vehicle and tire (:func:`layer_params`,
    :func:`layer_tire_scales`, layer major), then the airborne model (configured
    vehicle)."""
    kt = cfg.tire.stiffness_coefficient
    ground = [model for (M, K, C), t in zip(layer_params(cfg), layer_tire_scales(cfg),
                                            strict=True)
              for model in model_family(cfg.replace(vehicle={
                  "sprung_mass_kg": M, "suspension_stiffness_n_per_m": K,
                  "suspension_damping_ns_per_m": C}, tire={"stiffness_coefficient": kt * t}))
              if not model.airborne]
    return ground + [model for model in model_family(cfg) if model.airborne]


@pytest.fixture(scope="module")
def design(default_design: Design) -> Design:
    """The default design (conftest's, designed once per session)."""
    return default_design


def test_shapes_and_fields(design: Design) -> None:
    """The built-in bank, whatever its layers: each layer the three tire models of the
    configured deflections, then the one airborne model."""
    family = model_family(CFG)          # a layer's tire models + the airborne model
    assert len(family) == 4
    n_layers = len(layer_scales(CFG))
    J = n_layers * 3 + 1
    S = len(CFG.noise.speeds_mps) * len(CFG.noise.road_roughness_gd)
    assert design.n_models == J
    assert design.n_noise == S == 20
    assert design.lq_gain.shape == (2, J, 6)
    D = CFG.design.compute_delay_ticks
    assert design.compute_delay_ticks == D
    assert design.actuator_gain.shape == (2, J, 3 + D)
    np.testing.assert_array_equal(design.servo_model, servo_model(CFG).as_array())
    assert design.airborne.tolist() == [False] * (J - 1) + [True]
    assert design.grid_index.tolist() == [[0, 0], [1, 0], [2, 0]] * n_layers + [[-1, -1]]
    assert np.all(np.isnan(design.equilibrium[J - 1]))
    assert not np.any(np.isnan(design.equilibrium[:J - 1]))
    assert design.dt_s == pytest.approx(1e-3)
    assert design.y_offset.tolist() == [0.0, -CFG.vehicle.gravity_mps2]
    assert design.static_rattlespace_m == pytest.approx(500 * 9.80665 / 27.4e3)
    md = design.metadata
    assert md["artifact_version"] == ARTIFACT_VERSION
    assert md["config_hash"] == config_hash(CFG)
    for key in ("config_toml", "numpy_version", "scipy_version", "control_version",
                "created_utc"):
        assert md[key]


def test_gains_and_curve_are_the_component_results(design: Design) -> None:
    """Every model of the built-in bank (each layer's vehicle; the airborne model last)."""
    hf = human_filter(CFG.design, CFG.sample_time_s)
    models = bank_models(CFG)
    assert len(models) == design.n_models
    for j, model in enumerate(models):
        for w, ws in enumerate(CFG.design.weight_sets):
            k = actuated_lq_gain(model, hf, ws, servo_model(CFG))
            np.testing.assert_array_equal(design.lq_gain[w, j], k[:6])
            np.testing.assert_array_equal(design.actuator_gain[w, j], k[6:])
    assert np.all(design.lq_gain[:, -1] == 0.0)
    assert np.all(design.actuator_gain[:, -1] == 0.0)
    ideal = design_bank(CFG.replace(design={"actuator_model": "ideal"}))
    for j, model in enumerate(models):
        for w, ws in enumerate(CFG.design.weight_sets):
            np.testing.assert_array_equal(ideal.lq_gain[w, j], lq_gain(model, hf, ws))
    assert np.all(ideal.actuator_gain == 0.0)
    np.testing.assert_array_equal(design.human_filter_Ad, hf.Ad)
    for i in range(0, design.fuzzy_q_grid.size, 250):
        assert design.fuzzy_weight_curve[i] == firing_weight(float(design.fuzzy_q_grid[i]),
                                                             CFG.fuzzy)


def test_noise_table_order_and_monotonicity(design: Design) -> None:
    """s = i_speed * Nr + i_rough; more road noise -> larger innovation covariance."""
    Nr = design.noise_roughness_gd.size
    for j in range(3):
        dets = design.innovation_logdet[j]
        for i_s in range(design.noise_speeds_mps.size):
            row = dets[i_s * Nr:(i_s + 1) * Nr]
            assert np.all(np.diff(row) > 0)
    w = [road_velocity_intensity(v, g) for v in CFG.noise.speeds_mps
         for g in CFG.noise.road_roughness_gd]
    assert design.noise_index(2, 3) == 2 * Nr + 3
    assert w[design.noise_index(2, 3)] == pytest.approx(
        road_velocity_intensity(CFG.noise.speeds_mps[2], CFG.noise.road_roughness_gd[3]))


def test_every_filter_stable(design: Design) -> None:
    rho = np.max(np.abs(np.linalg.eigvals(design.filter_A)), axis=-1)
    assert np.all(rho < 1.0)


def test_save_load_round_trip(design: Design, tmp_path: Path) -> None:
    p = tmp_path / "design.npz"
    save_design(design, p)
    back = load_design(p, CFG)
    for f in Design.__dataclass_fields__:
        a, b = getattr(design, f), getattr(back, f)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
            assert a.dtype.kind == b.dtype.kind
        else:
            assert a == b


def test_config_mismatch_raises(design: Design, tmp_path: Path) -> None:
    p = tmp_path / "design.npz"
    save_design(design, p)
    other = CFG.replace(vehicle={"sprung_mass_kg": 450.0})
    with pytest.raises(DesignMismatch, match="rig design"):
        load_design(p, other)
    load_design(p)  # without a config no hash check


def test_artifact_check_covers_only_design_sections(design: Design, tmp_path: Path) -> None:
    """Service-only settings (telemetry, CAN, recording, safety) keep the artifact valid;
    a design input (vehicle mass, fuzzy, noise) does not."""
    p = tmp_path / "design.npz"
    save_design(design, p)
    assert design.metadata["design_config_hash"] == design_config_hash(CFG)
    service_only = CFG.replace(telemetry={"endpoints": ["tcp/127.0.0.1:17447"]},
                               can={"channel": "can3", "interface": "socketcan"},
                               recording={"directory": "elsewhere"},
                               safety={"heartbeat_hz": 20.0})
    assert config_hash(service_only) != config_hash(CFG)
    assert design_config_hash(service_only) == design_config_hash(CFG)
    load_design(p, service_only)
    for changed in (CFG.replace(vehicle={"sprung_mass_kg": CFG.vehicle.sprung_mass_kg + 1}),
                    CFG.replace(noise={"force_std_n": CFG.noise.force_std_n * 2}),
                    CFG.replace(force_loop={"kp_per_n": CFG.force_loop.kp_per_n * 2})):
        assert design_config_hash(changed) != design_config_hash(CFG)
        with pytest.raises(DesignMismatch, match="rig design"):
            load_design(p, changed)


def test_artifact_without_design_hash_uses_full_config_hash(design: Design,
                                                            tmp_path: Path) -> None:
    """Artifacts written before design_config_hash: checked against config_hash."""
    import dataclasses
    md = {k: v for k, v in design.metadata.items() if k != "design_config_hash"}
    p = tmp_path / "old.npz"
    save_design(dataclasses.replace(design, metadata=md), p)
    load_design(p, CFG)
    with pytest.raises(DesignMismatch):
        load_design(p, CFG.replace(telemetry={"rate_hz": 10.0}))


def test_version_and_corruption_detected(design: Design, tmp_path: Path) -> None:
    p = tmp_path / "design.npz"
    save_design(design, p)
    with np.load(p) as npz:
        data = {k: npz[k] for k in npz.files}
    meta = json.loads(str(data["metadata"]))
    meta["artifact_version"] = ARTIFACT_VERSION + 1
    bad = tmp_path / "v.npz"
    np.savez(bad, **{**data, "metadata": np.asarray(json.dumps(meta))})
    with pytest.raises(DesignMismatch, match="version"):
        load_design(bad)
    missing = tmp_path / "m.npz"
    np.savez(missing, **{k: v for k, v in data.items() if k != "kalman_gain"})
    with pytest.raises(DesignMismatch, match="kalman_gain"):
        load_design(missing)
    shape = tmp_path / "s.npz"
    np.savez(shape, **{**data, "lq_gain": data["lq_gain"][:, :, :5]})
    with pytest.raises(DesignMismatch, match="lq_gain"):
        load_design(shape)
    nan = tmp_path / "n.npz"
    fa = data["filter_A"].copy()
    fa[0, 0, 0, 0] = np.nan
    np.savez(nan, **{**data, "filter_A": fa})
    with pytest.raises(DesignMismatch, match="non-finite"):
        load_design(nan)
    junk = tmp_path / "j.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(DesignMismatch):
        load_design(junk)
    with pytest.raises(FileNotFoundError):
        load_design(tmp_path / "nope.npz")


def test_cli_design_writes_artifact_and_json(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """On the one-layer bank (the configured vehicle's tire models, by name): the JSON is
    the artifact's, and its rig-loop poles are controller.analysis's."""
    one = one_layer(CFG)
    out = tmp_path / "d.npz"
    assert main(["design", "--config", str(write_one_layer_config(tmp_path)),
                 "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["models"]) == {"x2_40mm", "x2_25mm", "x2_10mm", "airborne"}
    d = load_design(out, one)
    m = summary["models"]["x2_25mm"]
    np.testing.assert_allclose(m["lq"]["weight_set_1"]["gain"], d.lq_gain[0, 1])
    ideal = m["lq"]["weight_set_1"]["ideal_actuator_closed_loop_poles"]
    assert len(ideal) == 6 and all(p["abs"] < 1.0 for p in ideal)
    # the whole rig loop: LQG + PI + servo-hydraulics + compute delay, stable, and the
    # same spectrum as controller.analysis builds for `rig analyze`
    from controller.analysis import rig_closed_loop
    from controller.design import design_models
    md = design_models(one)[1]
    cl = rig_closed_loop(one, md, list(one.design.weight_sets[0]), "lqg",
                         one.design.compute_delay_ticks)
    poles = m["lq"]["weight_set_1"]["closed_loop_poles"]
    assert len(poles) == cl.A.shape[0] > 6 and all(p["abs"] < 1.0 for p in poles)
    # (the summary builds the loop from the artifact's gains; the same poles)
    np.testing.assert_allclose([p["abs"] for p in poles],
                               np.sort(np.abs(np.linalg.eigvals(cl.A)))[::-1], rtol=1e-9)
    assert "closed_loop_poles" not in summary["models"]["airborne"]["lq"]["weight_set_1"]
    # continuous equivalent of a discrete pole: |z| = exp(-zeta wn dt)
    for p in poles:
        assert p["abs"] == pytest.approx(np.exp(-p["zeta"] * p["wn_rad_s"] * d.dt_s), rel=1e-9)
    k = m["kalman"]
    np.testing.assert_allclose(k["gain"], d.kalman_gain[1, k["noise_entry"]])
    assert k["speed_mps"] == pytest.approx(one.noise.nominal_speed_mps)
    assert k["roughness_gd"] == pytest.approx(one.noise.nominal_roughness_gd)


def test_cli_design_plain_and_bad_config(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "d.npz"
    assert main(["design", "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[design]\nsample_rate_hz = -5\n")
    assert main(["design", "--config", str(bad), "--out", str(out)]) == 2
    assert "sample_rate_hz" in capsys.readouterr().err
