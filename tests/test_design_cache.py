"""rig.design_cache: a configuration is designed once, a hit is the same design with the
asking configuration's metadata, and a cache that is broken only costs the time."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import controller.design
from controller.artifact import _ARRAY_FIELDS, Design
from controller.config import config_hash, config_to_toml, default_config, one_layer
from rig import design_cache

CFG = one_layer(default_config())


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list[str]:
    """The cache in ``tmp_path/cache``; the design_bank calls made, by config hash."""
    monkeypatch.setenv(design_cache.ENV, str(tmp_path / "cache"))
    made: list[str] = []
    real = controller.design.design_bank

    def counting(cfg: Any) -> Design:
        made.append(config_hash(cfg))
        return real(cfg)

    monkeypatch.setattr(controller.design, "design_bank", counting)
    return made


def _same_arrays(a: Design, b: Design) -> None:
    for name in _ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert list(a.model_names) == list(b.model_names)


def test_second_request_is_read_back_bit_for_bit(calls: list[str], tmp_path: Path) -> None:
    first = design_cache.design_for(CFG)
    second = design_cache.design_for(CFG)
    assert len(calls) == 1
    _same_arrays(first, second)
    assert second.metadata == first.metadata
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1


def test_hit_for_another_configuration_carries_its_own_metadata(calls: list[str]) -> None:
    first = design_cache.design_for(CFG)
    other = CFG.replace(telemetry={"enabled": False})  # not a design section
    assert config_hash(other) != config_hash(CFG)
    got = design_cache.design_for(other)
    assert len(calls) == 1                                      # a hit
    _same_arrays(first, got)
    assert got.metadata["config_hash"] == config_hash(other)
    assert got.metadata["config_toml"] == config_to_toml(other)
    assert got.metadata["created_utc"] == first.metadata["created_utc"]


def test_a_design_section_change_is_designed_again(calls: list[str]) -> None:
    design_cache.design_for(CFG)
    design_cache.design_for(CFG.replace(vehicle={"sprung_mass_kg": 300.0}))
    assert len(calls) == 2


def test_a_bad_entry_is_designed_again_and_replaced(calls: list[str], tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    design_cache.design_for(CFG)
    (entry,) = (tmp_path / "cache").glob("*.npz")
    entry.write_bytes(b"not an artifact")
    with caplog.at_level(logging.WARNING, logger="rig.design_cache"):
        again = design_cache.design_for(CFG)
    assert len(calls) == 2
    again.validate()
    assert entry.stat().st_size > 1000                          # rewritten whole
    design_cache.design_for(CFG)
    assert len(calls) == 2


def test_an_unwritable_cache_only_costs_the_time(calls: list[str], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    monkeypatch.setenv(design_cache.ENV, str(blocker / "designs"))
    with caplog.at_level(logging.WARNING, logger="rig.design_cache"):
        d = design_cache.design_for(CFG)
    d.validate()
    assert len(calls) == 1
    assert "design cache: cannot write" in caplog.text


def test_off_designs_every_time_and_writes_nothing(calls: list[str], tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(design_cache.ENV, "off")
    design_cache.design_for(CFG)
    design_cache.design_for(CFG)
    assert len(calls) == 2
    assert not (tmp_path / "cache").exists()


def test_least_recently_used_entries_beyond_the_limit_go(calls: list[str], tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    monkeypatch.setattr(design_cache, "MAX_ENTRIES", 1)
    design_cache.design_for(CFG)
    design_cache.design_for(CFG.replace(vehicle={"sprung_mass_kg": 300.0}))
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1
    design_cache.design_for(CFG)                                # the first went
    assert len(calls) == 3


def test_directory_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in (design_cache.ENV, "CACHE_DIRECTORY", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", "/home/u")
    assert design_cache.cache_dir() == Path("/home/u/.cache/rig/designs")
    monkeypatch.setenv("XDG_CACHE_HOME", "/x")
    assert design_cache.cache_dir() == Path("/x/rig/designs")
    monkeypatch.setenv("CACHE_DIRECTORY", "/var/cache/rig")       # systemd CacheDirectory=
    assert design_cache.cache_dir() == Path("/var/cache/rig/designs")
    monkeypatch.setenv(design_cache.ENV, "OFF")
    assert design_cache.cache_dir() is None
