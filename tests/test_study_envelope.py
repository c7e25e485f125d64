"""The study's operating envelope (issue 22): the tire cases of the ballast sweep, the 25 %
Monte Carlo and the many road seeds (hil/study/matrix.py, hil/study/report.py)."""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from controller.config import default_config, load_config
from hil.sim.closed_loop import simulate
from hil.sim.montecarlo import run_montecarlo
from hil.sim.plant import P_KT, RigPlant
from hil.sim.roads import make_road
from hil.study.cases import Case, case_config, run_case
from hil.study.matrix import (
    DEFAULT_GROUPS,
    ENVELOPE_MC_CONTROLLERS,
    ENVELOPE_SEED_CONTROLLERS,
    GROUPS,
    envelope_cases,
    envelope_mc_cases,
    envelope_seed_cases,
    plan,
    selected,
)
from hil.study.report import _envelope, _envelope_mc, _envelope_seeds
from tests.support.profiles import THESIS_PROFILE

CFG = default_config()
DT = CFG.sample_time_s
V25 = 11.176


def test_tire_true_plant_design_runs_on_the_plant_it_is_designed_for() -> None:
    """A true-plant tire case designs one layer with the plant's tire stiffness law and
    emulates it as configured: the same tire stiffness as the layered case's emulated
    rig; a mass-only true-plant case keeps the configured tire (its design is unchanged)."""
    case = Case("envelope", "fuzzy", tire_stiffness_scale=0.7, design_mass="true-plant")
    true = case_config(CFG, case)
    lay = case_config(CFG, replace(case, design_mass="layered"))
    assert true.tire.stiffness_coefficient == pytest.approx(0.7 * CFG.tire.stiffness_coefficient)
    assert true.emulator.tire_stiffness_scale == 1.0 and true.vehicle == CFG.vehicle
    assert lay.emulator.tire_stiffness_scale == 0.7 and lay.tire == CFG.tire
    assert RigPlant(true).p[P_KT] == RigPlant(lay).p[P_KT]
    mass_only = case_config(CFG, Case("envelope", "fuzzy", sprung_mass_scale=1.3,
                                      design_mass="true-plant"))
    assert mass_only.tire == CFG.tire
    assert replace(case, controller="passive").ref_key() != replace(
        case, controller="passive", tire_stiffness_scale=1.3).ref_key()


def test_envelope_plan_covers_the_issue_cases() -> None:
    p = plan(False)
    env = envelope_cases(p)
    tags = {c.param_tag for c in env}
    assert {"Kt0.7", "Kt1.3", "M0.6", "M1.5"} <= tags
    assert len(env) == 2 * (len(p.envelope_mass_scales) + 2) * 6
    assert {c.observe_s for c in env} == {10.0}
    assert {c.label for c in env} == {"passive", "lqg-1 (one-layer)", "fuzzy-1 (layered)",
                                      "fuzzy-1 (true-plant)", "fuzzy-default (layered)",
                                      "fuzzy-default (true-plant)"}
    # the defaults are layered: the Monte Carlo compares them with the one-layer bank;
    # deploy/thesis.toml is one layer: with the layered bank
    mc = envelope_mc_cases(p, CFG)
    assert len(mc) == 2 * 20 * (1 + len(ENVELOPE_MC_CONTROLLERS) - 2)
    assert {c.duration_s for c in mc} == {20.0} and {c.road_seed for c in mc} == {1, 2}
    assert {c.label for c in mc} == {"passive", "fuzzy-1", "fuzzy-2", "fuzzy-default",
                                     "fuzzy-1 (one-layer)", "fuzzy-default (one-layer)"}
    assert {c.label for c in envelope_mc_cases(p, load_config(THESIS_PROFILE))} == {
        "passive", "fuzzy-1", "fuzzy-2", "fuzzy-default", "fuzzy-1 (layered)",
        "fuzzy-default (layered)"}
    seeds = envelope_seed_cases(p)
    assert len(seeds) == 12 * 13 and {c.duration_s for c in seeds} == {60.0}
    labels = {c.label for c in seeds}
    for mode in ("lqg", "fuzzy", "bayes", "moving"):
        assert {f"{mode}-1", f"{mode}-2", f"{mode}-default"} <= labels
    assert len(ENVELOPE_SEED_CONTROLLERS) == 12
    assert "envelope-seeds" in GROUPS and "envelope-seeds" not in DEFAULT_GROUPS
    assert selected(mc + seeds, ("envelope-mc",)) == mc
    with pytest.raises(ValueError, match="allowed"):
        selected(mc, ("nope",))


def test_envelope_mc_runs_are_rig_montecarlo_runs() -> None:
    """Each envelope-mc row is the run ``rig montecarlo --seed K`` makes of that plant."""
    p = replace(plan(True), envelope_mc_runs=2, envelope_mc_duration_s=0.4,
                envelope_mc_seeds=(2,))
    cases = [c for c in envelope_mc_cases(p, CFG) if c.label in ("passive", "fuzzy-2")]
    road = make_road("rough-course", V25, 0.4, DT, 2)
    for ctrl in ("passive", "fuzzy"):
        res = run_montecarlo(CFG, road, 2, controller=ctrl, weight_set=2, spread=0.25,
                             seed=2, workers=1, progress=False)
        mine = [c for c in cases if c.controller == ctrl]
        assert len(mine) == len(res.runs) == 2
        for case, run in zip(mine, res.runs, strict=True):
            row = run_case(case, CFG)
            assert case.params is not None
            assert run["sprung_mass_kg"] == case.params.sprung_mass_kg
            for key in ("absorbed_power", "rattlespace_peak_m", "bump_stop_time_s"):
                assert row[key] == run[key], (ctrl, key)


def test_envelope_seed_runs_are_rig_sim_runs() -> None:
    """A many-road-seeds row is ``rig sim --seed S`` of that controller; ``-default``
    runs the configuration's weight set."""
    p = replace(plan(True), envelope_road_seeds=(3,), envelope_road_duration_s=0.4)
    case = next(c for c in envelope_seed_cases(p) if c.label == "bayes-default")
    row = run_case(case, CFG)
    road = make_road("rough-course", V25, 0.4, DT, 3)
    ref = simulate(CFG, road, "bayes", CFG.design.weight_set, seed=3).metrics
    for key in ("absorbed_power", "rattlespace_rms_m", "force_rms_n"):
        assert row[key] == ref[key], key


def test_ballast_sweep_runs_are_observed_rig_sim_runs(capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    """A ballast-sweep row is ``rig sim --seed S --observe O`` on that plant: observed O s
    (the road O + D long), the metrics over the armed D s."""
    from rig.cli import main
    p = replace(plan(True), envelope_seeds=(2,), envelope_duration_s=0.4,
                envelope_observe_s=0.3, envelope_mass_scales=(1.0,), envelope_tire_scales=())
    case = next(c for c in envelope_cases(p) if c.label == "fuzzy-default (true-plant)")
    row = run_case(case, CFG)
    assert main(["sim", "--seed", "2", "--duration", "0.4", "--observe", "0.3",
                 "--controller", "fuzzy", "--json"]) == 0
    ref = json.loads(capsys.readouterr().out)
    for key in ("absorbed_power", "rattlespace_rms_m", "force_rms_n"):
        assert row[key] == ref[key], key


def _row(group: str, label: str, seed: int, tag: str = "nominal", **metrics: float
         ) -> dict[str, Any]:
    controller = label.split("-")[0]
    base = {"absorbed_power": 1.0, "absorbed_power_ratio": 1.0,
            "rattlespace_rms_m_ratio": 1.0, "rattlespace_peak_m_ratio": 1.0,
            "bump_stop_time_s": 0.0, "bump_stop_slam": 0.0, "n_faults": 0.0,
            "nonfinite": 0.0}
    base.update(metrics)
    return {"group": group, "label": label, "controller": controller, "road_seed": seed,
            "param_tag": tag, "duration_s": 60.0, **base}


def _cells(lines: list[str], first: str) -> list[str]:
    row = next(line for line in lines if line.startswith(f"| {first} |"))
    return [c.strip() for c in row.strip("|").split("|")]


def test_seed_table_budget_slams_and_faults() -> None:
    """Stop contact against passive's + 0.1 % of the run on the same seed, slams where
    passive does not slam, faults: each failing alone flips the verdict."""
    g = "envelope-seeds"
    rows = [_row(g, "passive", 1, bump_stop_time_s=0.05),
            _row(g, "passive", 2, bump_stop_time_s=0.5, bump_stop_slam=1.0),
            _row(g, "lqg-1", 1, bump_stop_time_s=0.10, absorbed_power_ratio=0.2),
            _row(g, "lqg-1", 2, bump_stop_time_s=0.55, bump_stop_slam=1.0,
                 absorbed_power_ratio=0.4),
            _row(g, "fuzzy-1", 1, bump_stop_time_s=0.12),     # 0.01 s over 0.05 + 0.06
            _row(g, "fuzzy-1", 2, bump_stop_time_s=0.5),
            _row(g, "bayes-1", 1, bump_stop_slam=1.0),        # passive does not slam
            _row(g, "bayes-1", 2),
            _row(g, "moving-1", 1, n_faults=1.0),
            _row(g, "moving-1", 2)]
    lines = _envelope_seeds(rows)
    lqg = _cells(lines, "lqg-1")
    assert lqg[1] == "2" and lqg[2].startswith("0.3 (") and lqg[-1] == "yes"
    assert lqg[6].startswith("0 (") and lqg[7] == "0" and lqg[8] == "1"
    fuzzy = _cells(lines, "fuzzy-1")
    assert fuzzy[6] == "1 (0.01)" and fuzzy[-1] == "**no**"
    bayes = _cells(lines, "bayes-1")
    assert bayes[7] == "1" and bayes[-1] == "**no**"
    moving = _cells(lines, "moving-1")
    assert moving[9] == "1" and moving[-1] == "**no**"
    assert _cells(lines, "passive")[-1] == "–"


def test_mc_table_counts_slams_on_the_same_plants_and_power_of_means() -> None:
    g = "envelope-mc"
    rows = [_row(g, "passive", 1, "p0", absorbed_power=1.0, bump_stop_slam=1.0),
            _row(g, "passive", 1, "p1", absorbed_power=3.0),
            _row(g, "fuzzy-1", 1, "p0", absorbed_power=0.2, bump_stop_slam=1.0),
            _row(g, "fuzzy-1", 1, "p1", absorbed_power=1.0),       # mean 0.6 / 2 = 0.3
            _row(g, "fuzzy-2", 1, "p0", absorbed_power=0.1),
            _row(g, "fuzzy-2", 1, "p1", absorbed_power=0.1, bump_stop_slam=1.0)]
    lines = _envelope_mc(rows)
    f1 = _cells(lines, "1 | fuzzy-1")
    assert f1[3:6] == ["1 (1)", "0", "0"] and f1[7] == "0.3" and f1[-1] == "yes"
    f2 = _cells(lines, "1 | fuzzy-2")
    assert f2[3:5] == ["1 (1)", "1"] and f2[-1] == "yes"   # at most passive's count
    rows.append(_row(g, "fuzzy-2", 1, "p2", absorbed_power=0.1, bump_stop_slam=1.0))
    assert _cells(_envelope_mc(rows), "1 | fuzzy-2")[-1] == "**no**"


def test_envelope_table_names_tire_plants_and_bounds() -> None:
    g = "envelope"

    def r(label: str, ap: float, rs: float, mass: float = 1.0, tire: float = 1.0
          ) -> dict[str, Any]:
        return {**_row(g, label, 1, absorbed_power_ratio=ap, rattlespace_rms_m_ratio=rs),
                "sprung_mass_scale": mass, "tire_stiffness_scale": tire}
    rows = [r("lqg-1", 0.1, 1.0, mass=0.7), r("fuzzy-1 (layered)", 0.109, 1.0, mass=0.7),
            r("fuzzy-1 (true-plant)", 0.1, 1.0, mass=0.7),
            r("fuzzy-default (layered)", 0.12, 1.0, mass=0.7),
            r("fuzzy-default (true-plant)", 0.1, 1.0, mass=0.7),
            r("lqg-1", 0.1, 1.0, tire=1.3), r("fuzzy-1 (layered)", 0.1, 1.06, tire=1.3),
            r("fuzzy-1 (true-plant)", 0.1, 1.0, tire=1.3)]
    lines = _envelope(rows)
    m07 = _cells(lines, "M x0.7")
    assert m07[-2].endswith(": yes") and m07[-1] == "1.200, 1.000: **no**"
    t13 = _cells(lines, "tire x1.3")
    assert t13[-2].endswith(": **no**") and t13[-1] == "–"      # the default law not run
    assert lines.index(next(x for x in lines if x.startswith("| M x0.7"))) < lines.index(
        next(x for x in lines if x.startswith("| tire x1.3")))


def test_groups_option() -> None:
    from rig.commands.study import groups
    assert groups("all") == GROUPS
    assert groups("envelope-seeds, main") == ("main", "envelope-seeds")
    with pytest.raises(argparse.ArgumentTypeError, match="nope"):
        groups("main,nope")


@pytest.mark.slow
def test_envelope_groups_alone_end_to_end(tmp_path: Path) -> None:
    """``rig study --quick --groups envelope,envelope-mc,envelope-seeds``: the three
    envelope tables and the ballast figure, no thesis tables and no claims.json."""
    from rig.cli import main
    out = tmp_path / "study"
    assert main(["study", "--quick", "--out", str(out), "--jobs", "1", "--no-progress",
                 "--groups", "envelope,envelope-mc,envelope-seeds"]) == 0
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "## Operating envelope: ballast sweep and tire stiffness" in md
    assert "| tire x0.7 |" in md and "| 1 | fuzzy-default |" in md
    assert "| moving-default |" in md and "## Thesis case" not in md
    assert not (out / "claims.json").exists() and (out / "fig_envelope_mass.png").exists()
    with (out / "results.csv").open(encoding="utf-8") as fh:
        groups_run = {r["group"] for r in csv.DictReader(fh)}
    assert groups_run == {"envelope", "envelope-mc", "envelope-seeds"}
