"""Configuration: defaults from NOTES.md, validation errors name key, value and range."""

from __future__ import annotations

import pytest

from controller.config import (
    LAYER_KEYS,
    MAX_CONFIG_BYTES,
    ConfigError,
    config_hash,
    config_to_toml,
    default_config,
    load_config,
    parse_config,
)


def test_defaults_match_notes() -> None:
    cfg = default_config()
    assert cfg.vehicle.sprung_mass_kg == 500.0
    assert cfg.vehicle.unsprung_mass_kg == 60.0
    assert cfg.vehicle.suspension_stiffness_n_per_m == pytest.approx(27.4e3)
    assert cfg.vehicle.suspension_damping_ns_per_m == pytest.approx(1.65e3)
    assert cfg.design.sample_rate_hz == 1000.0
    assert cfg.design.linearisation_deflections_m == [0.04, 0.025, 0.01]
    assert cfg.design.weight_sets == [[1.0, 1e2, 1e-8, 1.0], [1e1, 1e-1, 1e-8, 1.0]]
    assert cfg.design.weight_set == 0                  # the travel schedule (§12) ...
    assert cfg.design.schedule_weight_sets == [2, 1]   # ... from set 2 to set 1
    assert cfg.weights == (1e1, 1e-1, 1e-8, 1.0)       # its comfort set


def test_toml_round_trip(tmp_path) -> None:
    cfg = default_config().replace(vehicle={"sprung_mass_kg": 420.0}, design={"weight_set": 2})
    path = tmp_path / "rig.toml"
    path.write_text(config_to_toml(cfg))
    back = load_config(path)
    assert back == cfg
    assert config_hash(back) == config_hash(cfg) != config_hash(default_config())


@pytest.mark.parametrize(
    ("data", "key", "fragment"),
    [
        ({"vehicle": {"sprung_mass_kg": -3}}, "vehicle.sprung_mass_kg", "[1.0, 5000.0]"),
        ({"vehicle": {"sprung_mass_kg": "heavy"}}, "vehicle.sprung_mass_kg", "a number"),
        ({"vehicle": {"sprung_mas_kg": 3}}, "vehicle.sprung_mas_kg", "a known key"),
        ({"design": {"sample_rate_hz": 10}}, "design.sample_rate_hz", "[50.0, 20000.0]"),
        ({"design": {"weight_set": 3}}, "design.weight_set", "[1, 2]"),
        ({"design": {"linearisation_deflections_m": []}}, "design.linearisation_deflections_m",
         "non-empty list"),
        ({"design": {"linearisation_deflections_m": [0.01, -0.02]}},
         "design.linearisation_deflections_m[1]", "(0.0, 0.2]"),
        ({"fuzzy": {"med": [3, 1, 4, 6]}}, "fuzzy.med", "a <= b <= c <= d"),
        ({"can": {"interface": "carrier-pigeon"}}, "can.interface", "'socketcan'"),
        ({"safety": {"stale_ticks": 1.5}}, "safety.stale_ticks", "an integer"),
        ({"telemetry": {"enabled": 1}}, "telemetry.enabled", "true or false"),
        ({"telemetry": {"status_queries_per_s": 0}}, "telemetry.status_queries_per_s",
         "[0.1, 10000.0]"),
        ({"telemetry": {"status_burst": 0}}, "telemetry.status_burst", "[1, 100000]"),
        ({"telemetry": {"commands_per_s": 1e9}}, "telemetry.commands_per_s", "[0.1, 1000.0]"),
        ({"telemetry": {"command_burst": 2.5}}, "telemetry.command_burst", "an integer"),
        ({"moving_bank": {"active_models": 9}}, "moving_bank.active_models", "[1, 4]"),
        ({"vehicle": 5}, "vehicle", "a table"),
    ],
)
def test_bad_values_are_named(data: dict, key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.key == key
    assert fragment in str(info.value)


def test_nan_rejected() -> None:
    with pytest.raises(ConfigError, match="finite"):
        parse_config({"vehicle": {"sprung_mass_kg": float("nan")}})


def test_bad_file_is_a_config_error(tmp_path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text("[vehicle\nsprung_mass_kg = 1")
    with pytest.raises(ConfigError, match="valid TOML"):
        load_config(p)
    with pytest.raises(ConfigError, match="readable"):
        load_config(tmp_path / "missing.toml")


def test_grid_and_table_sizes_are_bounded_with_the_reason() -> None:
    grid = [0.001 + i * 1e-7 for i in range(200_000)]
    with pytest.raises(ConfigError) as info:
        parse_config({"design": {"linearisation_deflections_m": grid}})
    msg = str(info.value)
    assert info.value.key == "design.linearisation_deflections_m"
    assert "at most 64 entries" in msg and "models in the bank" in msg
    assert "(200000 entries)" in msg and len(msg) < 400     # one short line
    # 20 deflections x 4 scales = 80 models (each list within its own bound)
    with pytest.raises(ConfigError,
                       match=r"at most 64 models in a layer of the bank: 20 deflections"):
        parse_config({"design": {"linearisation_deflections_m": grid[:20],
                                 "tire_damping_scales": [0.5, 1.0, 1.5, 2.0]}})
    # 4 models x 64 speeds x 50 roughness = 12800 Kalman designs
    speeds = [1.0 + i for i in range(64)]
    gd = [1e-6 * (i + 1) for i in range(50)]
    with pytest.raises(ConfigError, match=r"at most 12000 Kalman designs: 4 models x 64"):
        parse_config({"noise": {"speeds_mps": speeds, "road_roughness_gd": gd,
                                "nominal_roughness_gd": gd[3]},
                      "design": {key: [1.0] for key in LAYER_KEYS}})     # one layer
    # the layered default: 189 layers x 3 tire models + the airborne model
    with pytest.raises(ConfigError, match=r"12000 Kalman designs: 568 models x 64 speeds"):
        parse_config({"noise": {"speeds_mps": speeds, "road_roughness_gd": gd,
                                "nominal_roughness_gd": gd[3]}})
    with pytest.raises(ConfigError, match=r"at most 15 entries \(design.weight_set"):
        parse_config({"design": {"weight_sets": [[1.0, 1.0, 1e-8, 1.0]] * 16}})
    # every list key has a bound, also those without their own
    with pytest.raises(ConfigError, match="at most 64 entries"):
        parse_config({"telemetry": {"endpoints": ["tcp/127.0.0.1:7447"] * 65}})


def test_unreadable_files_are_config_errors(tmp_path) -> None:
    latin = tmp_path / "latin1.toml"
    latin.write_bytes('[can]\nchannel = "r\xe9seau"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match="byte 0xe9 at offset 18 is not UTF-8"):
        load_config(latin)
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 3000 + "]" * 3000)
    with pytest.raises(ConfigError, match="nested at most"):
        load_config(deep)
    big = tmp_path / "big.toml"
    with big.open("wb") as f:
        f.truncate(MAX_CONFIG_BYTES + 1)            # sparse: no disk used
    with pytest.raises(ConfigError, match="at most"):
        load_config(big)
    with pytest.raises(ConfigError, match="it is a character device"):
        load_config("/dev/zero")
    with pytest.raises(ConfigError, match="readable"):
        load_config(tmp_path)
