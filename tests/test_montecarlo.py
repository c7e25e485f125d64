"""Monte Carlo robustness runs (hil/sim/montecarlo.py, ``rig montecarlo``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from controller.config import default_config
from hil.sim.closed_loop import simulate
from hil.sim.montecarlo import RIDE_HEIGHT_STD_M, draw_params, run_montecarlo, summarise
from hil.sim.roads import make_road
from rig.cli import main

CFG = default_config()
DT = CFG.sample_time_s


def test_draws_are_normal_around_nominal_and_reproducible() -> None:
    params = draw_params(CFG, 4000, 0.05, seed=3)
    v = CFG.vehicle
    f = np.array([[p.sprung_mass_kg, p.unsprung_mass_kg, p.suspension_stiffness_n_per_m,
                   p.suspension_damping_ns_per_m, p.tire_stiffness_scale,
                   p.tire_damping_scale] for p in params], dtype=float)
    f /= np.array([v.sprung_mass_kg, v.unsprung_mass_kg, v.suspension_stiffness_n_per_m,
                   v.suspension_damping_ns_per_m, 1.0, 1.0])
    np.testing.assert_allclose(f.mean(axis=0), 1.0, atol=0.005)
    np.testing.assert_allclose(f.std(axis=0), 0.05, rtol=0.06)
    assert np.abs(np.corrcoef(f.T) - np.eye(6)).max() < 0.06      # independent draws
    assert draw_params(CFG, 3, 0.05, seed=3) == params[:3]
    per = draw_params(CFG, 500, {"M": 0.1, "K": 0.0}, seed=1)
    masses = np.array([p.sprung_mass_kg for p in per], dtype=float)
    assert np.std(masses) / v.sprung_mass_kg == pytest.approx(0.1, rel=0.1)
    assert {p.suspension_stiffness_n_per_m for p in per} == {v.suspension_stiffness_n_per_m}


@pytest.mark.parametrize("bad", [-0.1, 0.9, float("nan"), {"X": 0.1}])
def test_bad_spread_rejected(bad: object) -> None:
    with pytest.raises(ValueError):
        draw_params(CFG, 2, bad)  # type: ignore[arg-type]


def test_summary_matches_numpy() -> None:
    rows = [{"a": 1.0, "b": 2.0}, {"a": 3.0, "b": float("nan")}, {"a": 5.0, "b": 4.0}]
    s = summarise(rows)
    assert s["a"] == {"mean": 3.0, "std": pytest.approx(np.std([1, 3, 5])), "min": 1.0,
                      "max": 5.0}
    assert s["b"]["mean"] == 3.0


def test_ride_height_is_its_own_normal_parameter() -> None:
    """The ride height (static rattlespace about the stops' centre, set by preload) is
    N(0, std) from its own stream: the M..Ct draws do not change with it."""
    params = draw_params(CFG, 4000, 0.15, seed=5)
    off = np.array([p.ride_height_offset_m for p in params], dtype=float)
    assert abs(off.mean()) < 4 * RIDE_HEIGHT_STD_M / np.sqrt(off.size)
    assert off.std() == pytest.approx(RIDE_HEIGHT_STD_M, rel=0.05)
    masses = np.array([p.sprung_mass_kg for p in params], dtype=float)
    assert abs(np.corrcoef(masses, off)[0, 1]) < 0.06
    plain = draw_params(CFG, 4000, 0.15, seed=5, ride_height_std_m=None)
    assert all(p.ride_height_offset_m is None for p in plain)
    assert [p.sprung_mass_kg for p in plain] == [p.sprung_mass_kg for p in params]
    with pytest.raises(ValueError, match="ride_height_std_m"):
        draw_params(CFG, 2, 0.05, ride_height_std_m=-0.001)


def test_preload_puts_a_perturbed_plant_at_its_drawn_ride_height() -> None:
    """A +15 % mass / -15 % spring plant would sit (M g / K - M_nom g / K_nom) ~ 63 mm off
    the stops' centre; with the preload set it sits at the drawn offset, and its passive
    run (LVDT zeroed at rest) matches the nominal plant's dynamics."""
    from hil.sim.plant import P_R0, PlantParams, RigPlant
    v = CFG.vehicle
    heavy = dict(sprung_mass_kg=1.15 * v.sprung_mass_kg,
                 suspension_stiffness_n_per_m=0.85 * v.suspension_stiffness_n_per_m)
    loose = RigPlant(CFG, PlantParams(**heavy))
    eq = loose.equilibrium()
    assert eq[0] - eq[1] - loose.p[P_R0] == pytest.approx(
        1.15 * v.sprung_mass_kg * v.gravity_mps2 / (0.85 * v.suspension_stiffness_n_per_m)
        - v.sprung_mass_kg * v.gravity_mps2 / v.suspension_stiffness_n_per_m, rel=1e-12)
    set_ = RigPlant(CFG, PlantParams(**heavy, ride_height_offset_m=0.003))
    eq = set_.equilibrium()
    assert eq[0] - eq[1] - set_.p[P_R0] == pytest.approx(0.003, abs=1e-12)
    set_.reset()
    for _ in range(200):                  # at rest it stays there (a true equilibrium)
        set_.advance(DT, 0.0, True, 0.0, 0.0)
    assert set_.rattlespace_m - set_.p[P_R0] == pytest.approx(0.003, abs=1e-9)


def test_zero_spread_runs_reproduce_the_nominal_run_in_parallel(tmp_path: Path) -> None:
    road = make_road("bump", 11.176, 1.5, DT)
    res = run_montecarlo(CFG, road, 3, controller="passive", spread=0.0, workers=2,
                         progress=False, out_dir=tmp_path, ride_height_std_m=0.0)
    nominal = simulate(CFG, road, "passive").metrics
    for key in ("absorbed_power", "rattlespace_peak_m", "tire_load_rms_ratio"):
        assert res.summary[key]["std"] == 0.0
        assert res.summary[key]["mean"] == pytest.approx(nominal[key], rel=1e-12)
    assert res.unstable_runs == [] and len(res.traces) == 3
    png = Path(res.png or "")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "montecarlo.json").exists()


def test_active_runs_and_unstable_detection() -> None:
    road = make_road("rough-course", 11.176, 2.0, DT, seed=2)
    res = run_montecarlo(CFG, road, 2, controller="fuzzy", spread=0.05, workers=1,
                         progress=False)
    assert len(res.runs) == 2 and res.unstable_runs == []
    assert res.summary["force_rms_n"]["min"] > 0.0
    tight = CFG.replace(vehicle={"rattlespace_travel_m": 0.006})
    bump = make_road("bump", 11.176, 1.5, DT)
    res = run_montecarlo(tight, bump, 2, controller="passive", workers=1, progress=False)
    assert res.unstable_runs == [0, 1]


def test_observed_runs_are_observed_rig_sim_runs(capsys: pytest.CaptureFixture[str]
                                                ) -> None:
    """``rig montecarlo --observe S``: each run is ``simulate(..., observe_s=S)`` of its
    plant on the S + duration road, metrics over the armed time."""
    assert main(["montecarlo", "--runs", "2", "--duration", "0.4", "--observe", "0.3",
                 "--seed", "3", "--jobs", "1", "--no-progress", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    road = make_road("rough-course", 11.176, 0.7, DT, seed=3)
    plants = draw_params(CFG, 2, 0.05, 3, RIDE_HEIGHT_STD_M)
    want = [simulate(CFG, road, "fuzzy", CFG.design.weight_set, params=p, seed=3 + 1000 + i,
                     observe_s=0.3).metrics["absorbed_power"] for i, p in enumerate(plants)]
    assert out["summary"]["absorbed_power"]["min"] == min(want)
    assert out["summary"]["absorbed_power"]["max"] == max(want)


def test_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["montecarlo", "--runs", "2", "--duration", "1", "--road", "bump",
               "--controller", "passive", "--jobs", "1", "--no-progress",
               "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "absorbed_power" in out and "unstable runs: none" in out
    assert (tmp_path / "montecarlo.png").exists()
    assert main(["montecarlo", "--runs", "2", "--road", "nowhere", "--no-progress"]) == 2
    for c in ("zero-force", "skyhook"):
        assert main(["montecarlo", "--runs", "2", "--duration", "1", "--road", "iso-B",
                     "--controller", c, "--jobs", "1", "--no-progress", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["faulted_runs"] == [] and out["summary"]["force_rms_n"]["min"] > 0.0


@pytest.mark.parametrize(("argv", "expected"), [
    ([], RIDE_HEIGHT_STD_M), (["--ride-height-std", "0.004"], 0.004),
    (["--own-ride-height"], None), (["--own-ride-height", "--ride-height-std", "0.004"], None)])
def test_cli_ride_height_options(monkeypatch: pytest.MonkeyPatch, argv: list[str],
                                 expected: float | None) -> None:
    """``--ride-height-std`` sets the preload's setting error, ``--own-ride-height`` keeps
    each plant at its own M g / K (what the runs get: ``ride_height_std_m``)."""
    import rig.commands.montecarlo as cmd
    seen: dict[str, object] = {}

    def fake(cfg: object, road: object, runs: int, **kw: object) -> object:
        seen.update(kw)
        raise ValueError("stop here")

    monkeypatch.setattr(cmd, "run_montecarlo", fake)
    assert main(["montecarlo", "--runs", "2", "--duration", "1", "--no-progress",
                 *argv]) == 2
    assert seen["ride_height_std_m"] == expected
