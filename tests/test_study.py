"""Control performance study (hil/study, hil/skyhook.py, hil/fullstate.py, rig study)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.analysis import analyze
from controller.config import default_config
from hil.fullstate import FullStateLQ
from hil.plant import RigPlant
from hil.roads import make_road
from hil.sensors import SensorReading
from hil.sim import cached_design, simulate
from hil.skyhook import SkyhookController, SkyhookGains, select_gains
from hil.study.cases import Case, run_case, study_road
from hil.study.loop import BankController, lq_cost, run_closed_loop
from hil.study.matrix import RATIO_METRICS, add_ratios
from hil.study.report import LABEL_ORDER
from hil.study.tradeoff import tradeoff_grid

CFG = default_config()
DT = CFG.sample_time_s
V25 = 11.176
READING = SensorReading(0.0, 0.0, 0.0, 0)


# ----------------------------------------------------------------------- the closed loop


@pytest.mark.parametrize("controller", ["passive", "fuzzy", "moving"])
def test_loop_reproduces_simulate_bit_for_bit(controller: str) -> None:
    road = make_road("rough-course", V25, 1.5, DT, seed=4)
    ref = simulate(CFG, road, controller, 1, seed=9, settle_s=0.2).metrics
    ctrl = None if controller == "passive" else BankController(
        cached_design(CFG), CFG, controller, 1, road)
    got = run_closed_loop(CFG, road, ctrl, seed=9, settle_s=0.2).metrics
    for key, value in ref.items():
        if key != "realtime_factor":
            assert got[key] == value, key


def test_loop_delay_is_exact_number_of_ticks() -> None:
    road = make_road("bump", V25, 1.0, DT)
    for d in (1, 3):
        tr = run_closed_loop(CFG, road, SkyhookController(CFG), delay_ticks=d).traces
        np.testing.assert_array_equal(tr["spool_cmd"][d:], tr["spool_computed"][:-d])
        assert np.all(tr["spool_cmd"][:d] == 0.0)
        assert np.any(tr["spool_cmd"] != 0.0)
    a = run_closed_loop(CFG, road, SkyhookController(CFG), delay_point="force_ref").metrics
    b = run_closed_loop(CFG, road, SkyhookController(CFG), delay_point="spool").metrics
    assert a == b      # no delay: both placements are the same loop
    with pytest.raises(ValueError, match="delay_point"):
        run_closed_loop(CFG, road, None, delay_point="valve")


def test_lq_cost_is_eq_2_5() -> None:
    m = {"absorbed_power": 2.0, "tire_deflection_rms_m": 3.0, "rattlespace_rms_m": 5.0,
         "force_rms_n": 7.0}
    assert lq_cost(m, (1.0, 10.0, 0.1, 2.0)) == pytest.approx(2 * 2 + 9 + 10 * 25 + 0.1 * 49)


# ----------------------------------------------------------------------------- skyhook


def test_skyhook_velocity_estimates_match_closed_forms() -> None:
    g = SkyhookGains(c_sky_ns_per_m=2000.0, c_ground_ns_per_m=500.0, damper_cancel=0.5)
    sk = SkyhookController(CFG, g)
    a, rate, n = 0.7, 0.02, 3000
    leak = math.exp(-2 * math.pi * g.velocity_highpass_hz * DT)
    for k in range(n):
        u = sk.force(rate * k * DT, a)
    vs = a * DT * (1 - leak**n) / (1 - leak)          # leaky integral of a constant
    assert sk.body_velocity_mps == pytest.approx(vs, rel=1e-9)
    assert sk.rattle_rate_mps == pytest.approx(rate, rel=1e-9)   # ramp rate, settled
    c = CFG.vehicle.suspension_damping_ns_per_m
    assert u == pytest.approx(-2000 * vs + 500 * (vs + rate) - 0.5 * c * rate, rel=1e-9)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 3e4), st.floats(0.0, 3e4), st.floats(0.0, 1.0),
       st.lists(st.tuples(st.floats(-0.05, 0.05), st.floats(-20, 20)), min_size=2,
                max_size=20))
def test_skyhook_force_is_linear_in_gains(cs: float, cg: float, kc: float,
                                          seq: list[tuple[float, float]]) -> None:
    parts = [SkyhookController(CFG, SkyhookGains(*x)) for x in
             ((cs, 0.0, 0.0), (0.0, cg, 0.0), (0.0, 0.0, kc))]
    total = SkyhookController(CFG, SkyhookGains(cs, cg, kc))
    for r, a in seq:
        u = total.force(r, a)
        assert u == pytest.approx(sum(p.force(r, a) for p in parts), rel=1e-9, abs=1e-6)


def test_skyhook_bad_input_flags_fault_and_bad_gains_raise() -> None:
    sk = SkyhookController(CFG)
    assert sk.force(math.nan, 0.0) == 0.0 and sk.fault
    sk.reset()
    assert not sk.fault
    with pytest.raises(ValueError, match="c_sky"):
        SkyhookGains(c_sky_ns_per_m=-1.0)
    with pytest.raises(ValueError, match="damper_cancel"):
        SkyhookGains(damper_cancel=1.5)


def test_select_gains_rules() -> None:
    def row(cs: float, ap: float, rs: float, tl: float) -> dict[str, float]:
        return {"c_sky_ns_per_m": cs, "c_ground_ns_per_m": 0.0, "damper_cancel": 0.0,
                "absorbed_power_ratio": ap, "rattlespace_rms_m_ratio": rs,
                "tire_load_rms_ratio_ratio": tl, "unstable": 0.0}
    rows = [row(1, 0.9, 0.9, 1.0), row(2, 0.5, 0.99, 1.2), row(3, 0.2, 1.3, 1.0)]
    assert select_gains(rows).c_sky_ns_per_m == 2        # best feasible, not best overall
    assert select_gains([row(3, 0.2, 1.3, 1.0), row(4, 0.1, 1.1, 1.0)]).c_sky_ns_per_m == 4
    with pytest.raises(ValueError):
        select_gains([])


# -------------------------------------------------------------------------- full state


def test_fullstate_force_is_the_lq_law() -> None:
    design = cached_design(CFG)
    fs = FullStateLQ(design, CFG, weight_set=2)
    plant = RigPlant(CFG)
    xbar = plant.equilibrium()
    assert fs.step(READING, plant) == pytest.approx(0.0, abs=1e-6)   # rest: no force
    K = design.lq_gain[1, fs.model]
    dx = np.array([1e-3, -2e-3, 0.1, -0.3])
    fs.reset()
    fs.xf[:] = [0.01, -0.02]
    xf0 = fs.xf.copy()
    u = fs.force(xbar + dx, xbar, 1.5)
    assert u == pytest.approx(-(K[:4] @ dx) - K[4:] @ xf0, rel=1e-12)
    np.testing.assert_allclose(fs.xf, design.human_filter_Ad @ xf0
                               + design.human_filter_Bd * 1.5, rtol=1e-12)
    assert fs.force(xbar, xbar, math.inf) == 0.0 and fs.fault
    with pytest.raises(ValueError):
        FullStateLQ(design, CFG, weight_set=3)


@pytest.mark.parametrize("weight_set", [1, 2])
def test_fullstate_beats_lqg_on_the_lq_cost_in_the_linear_range(weight_set: int) -> None:
    """States known can only help *the cost the gain minimises* (Eq. 2.5).  Not absorbed
    power alone: the LQG may trade rattlespace for comfort (controller.analysis gives
    LQG a slightly lower absorbed power than LQ with weight set 1)."""
    road = make_road("iso-B", 10.0, 8.0, DT, seed=2)
    design = cached_design(CFG)
    w = CFG.design.weight_sets[weight_set - 1]
    full = run_closed_loop(CFG, road, FullStateLQ(design, CFG, weight_set), seed=5,
                           settle_s=1.0).metrics
    lqg = run_closed_loop(CFG, road, BankController(design, CFG, "lqg", weight_set, road),
                          seed=5, settle_s=1.0).metrics
    assert full["time_off_ground_s"] == 0.0 and lqg["time_off_ground_s"] == 0.0  # linear
    assert lq_cost(full, w) <= lq_cost(lqg, w)


# ------------------------------------------------------------------ trade-off, roads


def test_tradeoff_grid_matches_controller_analysis_at_the_thesis_sets() -> None:
    sets = CFG.design.weight_sets
    grid = tradeoff_grid(CFG, [sets[0][0], sets[1][0]], [sets[0][1], sets[1][1]])
    for i, ws in ((0, 1), (1, 2)):
        ref = analyze(CFG, ws)[grid.model]
        j = i
        for kind, d in (("lq", grid.lq), ("lqg", grid.lqg)):
            assert d["absorbed_power"][i, j] == pytest.approx(
                ref[kind]["absorbed_power_ratio"], rel=1e-9)
            assert d["rattlespace_rms"][i, j] == pytest.approx(
                ref[kind]["rattlespace_rms_ratio"], rel=1e-9)


def test_study_road_decimates_one_profile() -> None:
    fine = make_road("rough-course", V25, 2.0, 1 / 4000, seed=3)
    for rate in (250.0, 1000.0, 2000.0):
        r = study_road("rough-course", V25, 2.0, 1 / rate, 3)
        m = round(4000 / rate)
        np.testing.assert_array_equal(r.height_m, fine.height_m[::m])
        # held mean velocity integrates back onto the profile at every tick
        h = np.concatenate([[0.0], np.cumsum(r.velocity_mps) * r.dt_s])[:-1]
        np.testing.assert_allclose(h, r.height_m, atol=1e-12)


def test_ratios_against_matching_passive_run() -> None:
    cases = [Case("g", "passive", duration_s=1.0), Case("g", "skyhook", duration_s=1.0),
             Case("g", "skyhook", duration_s=1.0, road_seed=2)]
    rows = [run_case(c, CFG) for c in cases]
    add_ratios(rows, cases)
    for m in RATIO_METRICS:
        assert rows[0][f"{m}_ratio"] == 1.0
        assert rows[1][f"{m}_ratio"] == pytest.approx(rows[1][m] / rows[0][m])
        assert math.isnan(rows[2][f"{m}_ratio"])     # no passive run of that road seed


# ----------------------------------------------------------------- end to end, claims


@pytest.mark.slow
def test_quick_study_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from rig.cli import main
    out = tmp_path / "study"
    assert main(["study", "--quick", "--out", str(out), "--jobs", "2", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "runs in" in text and "weight set 1" in text
    md = (out / "results.md").read_text(encoding="utf-8")
    for lab in LABEL_ORDER:
        assert f"| {lab} |" in md
    with (out / "results.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) > 50
    ratio_keys = [f"{m}_ratio" for m in RATIO_METRICS]
    groups = {r["group"] for r in rows}
    assert {"tune", "main", "mc5", "mismatch", "delay", "rate", "rho"} <= groups
    for r in rows:
        vals = [float(r[k]) for k in ratio_keys]
        if r["controller"] == "passive":
            assert vals == [1.0] * len(vals), r["label"]
        assert all(math.isfinite(v) for v in vals), (r["group"], r["label"])
    claims = json.loads((out / "claims.json").read_text())
    assert len(claims["claims"]) == 5
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) >= 10
    for p in pngs:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) < 200_000, p.name


def _thesis_case(controller: str, ws: int, seed: int) -> dict[str, float]:
    return run_case(Case("claims", controller, ws, "rough-course", V25, 60.0, seed,
                         settle_s=1.0), CFG)


@pytest.fixture(scope="module")
def thesis_runs() -> dict[tuple[str, int], list[dict[str, float]]]:
    cases = {(c, ws): [_thesis_case(c, ws, s) for s in (1, 2, 3)]
             for c, ws in (("passive", 1), ("fuzzy", 1), ("fuzzy", 2))}
    return cases


def _ratio(runs: dict[tuple[str, int], list[dict[str, float]]], ws: int,
           key: str) -> list[float]:
    return [a[key] / p[key] for a, p in zip(runs[("fuzzy", ws)], runs[("passive", 1)],
                                            strict=True)]


@pytest.mark.slow
def test_thesis_claim_weight_set_1_halves_absorbed_power(thesis_runs: dict) -> None:
    assert max(_ratio(thesis_runs, 1, "absorbed_power")) <= 0.5


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="docs/study.md: the blended bank raises rattlespace "
                   "RMS ~10 % above passive on the 1.35 in course (rho2 = 100 is not "
                   "enough; linear analysis: LQG ratio 1.02, plus wheel hop)")
def test_thesis_claim_weight_set_1_rattlespace_not_above_passive(thesis_runs: dict) -> None:
    assert max(_ratio(thesis_runs, 1, "rattlespace_rms_m")) <= 1.0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="docs/study.md: the fuzzy bank with weight set 2 "
                   "absorbs more power than with set 1 (firing weights ~1/3 each blend "
                   "three different gains; single LQG and full-state LQ do improve)")
def test_thesis_claim_weight_set_2_reduces_absorbed_power_further(thesis_runs: dict) -> None:
    assert np.mean(_ratio(thesis_runs, 2, "absorbed_power")) < np.mean(
        _ratio(thesis_runs, 1, "absorbed_power"))


@pytest.mark.slow
def test_thesis_claim_weight_set_2_peak_travel_not_above_passive(thesis_runs: dict) -> None:
    assert max(_ratio(thesis_runs, 2, "rattlespace_peak_m")) <= 1.0
