"""Fast offline closed-loop simulator, metrics and ``rig sim``
(hil/sim/closed_loop.py, controller/metrics.py)."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
from scipy import signal

from controller.config import default_config
from controller.metrics import WK_TABLE, compute_metrics, filter_signal, human_filter_tf, wk_tf
from controller.runtime.force_loop import PIForceLoop
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop, simulate
from hil.sim.plant import RigPlant
from hil.sim.roads import make_road
from hil.sim.sensors import SensorReading
from rig.cli import main

CFG = default_config()
DT = CFG.sample_time_s
SPEED_25MPH = 11.176


@pytest.mark.parametrize("f_hz", sorted(WK_TABLE))
def test_wk_gain_matches_iso_2631_table(f_hz: float) -> None:
    num, den = wk_tf()
    _, h = signal.freqs(num, den, [2 * math.pi * f_hz])
    assert abs(h[0]) == pytest.approx(WK_TABLE[f_hz], rel=0.01)


@pytest.mark.parametrize(("tf", "f_hz"), [("human", 2.0), ("human", 8.0), ("wk", 5.0),
                                          ("wk", 20.0)])
def test_discrete_filters_match_continuous_gain(tf: str, f_hz: float) -> None:
    num, den = human_filter_tf() if tf == "human" else wk_tf()
    t = np.arange(20000) * DT
    y = filter_signal(np.sin(2 * math.pi * f_hz * t), num, den, DT)[10000:]
    _, h = signal.freqs(num, den, [2 * math.pi * f_hz])
    assert np.sqrt(2 * np.mean(y**2)) == pytest.approx(abs(h[0]), rel=0.01)


def test_metrics_on_synthetic_traces() -> None:
    n = 10000
    t = np.arange(n) * DT
    acc = 2.0 * np.sin(2 * math.pi * 3.0 * t)
    rattle = 0.01 * np.cos(2 * math.pi * 1.0 * t)
    tire = 5000.0 + 500.0 * np.sin(2 * math.pi * 7.0 * t)
    off = np.where(np.arange(n) % 100 == 0, DT, 0.0)
    m = compute_metrics(DT, acc, rattle, tire, 5000.0, np.full(n, 3.0), np.ones(n), off)
    assert m["accel_rms_mps2"] == pytest.approx(2 / math.sqrt(2), rel=1e-3)
    assert m["accel_peak_mps2"] == pytest.approx(2.0, rel=1e-3)
    assert m["rattlespace_rms_m"] == pytest.approx(0.01 / math.sqrt(2), rel=1e-3)
    assert m["rattlespace_peak_m"] == pytest.approx(0.01)
    assert m["tire_load_rms_ratio"] == pytest.approx(500 / math.sqrt(2) / 5000, rel=1e-3)
    assert m["time_off_ground_fraction"] == pytest.approx(0.01)
    assert m["force_rms_n"] == pytest.approx(3.0)
    _, h = signal.freqs(*human_filter_tf(), [2 * math.pi * 3.0])
    assert m["absorbed_power"] == pytest.approx((2 * abs(h[0])) ** 2 / 2, rel=0.05)


def _digest(res) -> str:
    h = hashlib.sha256()
    for k in sorted(res.traces):
        h.update(res.traces[k].tobytes())
    return h.hexdigest()


def test_same_seed_bit_identical_run() -> None:
    road = make_road("rough-course", SPEED_25MPH, 1.0, DT, seed=4)
    a = simulate(CFG, road, "fuzzy", 1, seed=4)
    b = simulate(CFG, road, "fuzzy", 1, seed=4)
    c = simulate(CFG, road, "fuzzy", 1, seed=5)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


def test_passive_run_is_passive_and_stable() -> None:
    road = make_road("rough-course", SPEED_25MPH, 5.0, DT, seed=2)
    res = simulate(CFG, road, "passive")
    m = res.metrics
    assert m["force_rms_n"] < 1e-9 and m["hydraulic_power_mean_w"] == 0.0
    assert m["unstable"] == 0.0 and m["n_faults"] == 0.0
    assert 0.5 < m["accel_rms_mps2"] < 5.0
    assert np.all(res.traces["spool_cmd"] == 0.0)


def test_fuzzy_lowers_absorbed_power_on_the_rough_course() -> None:
    """Thesis Ch. V: 1.35 in RMS course at 25 mph; the active run absorbs less power."""
    road = make_road("rough-course", SPEED_25MPH, 8.0, DT, seed=1)
    passive = simulate(CFG, road, "passive", settle_s=0.5).metrics
    fuzzy = simulate(CFG, road, "fuzzy", 1, settle_s=0.5).metrics
    assert fuzzy["unstable"] == 0.0 and fuzzy["n_faults"] == 0.0
    assert fuzzy["absorbed_power"] < 0.5 * passive["absorbed_power"]
    assert fuzzy["wk_rms_mps2"] < passive["wk_rms_mps2"]
    assert fuzzy["force_rms_n"] > 100.0


def test_loop_delay_and_sample_rate_options() -> None:
    road = make_road("bump", SPEED_25MPH, 1.5, DT)
    res = simulate(CFG, road, "fuzzy", 1, delay_ticks=3)
    ref, spool = res.traces["force_ref_n"], res.traces["spool_cmd"]
    assert np.all(np.isfinite(ref)) and res.metrics["nonfinite"] == 0.0
    assert np.all(spool[:3] == 0.0) and np.any(spool != 0.0)
    # exactly 3 ticks between computing a command and the valve applying it
    computed = res.traces["spool_computed"]
    np.testing.assert_array_equal(spool[3:], computed[:-3])
    # the valve sees the command computed 3 ticks earlier: with no delay the first tick
    # already moves the spool
    assert simulate(CFG, road, "fuzzy", 1).traces["spool_cmd"][0] != 0.0
    cfg500 = CFG.replace(design={"sample_rate_hz": 500.0})
    road500 = make_road("bump", SPEED_25MPH, 1.5, 1 / 500)
    res500 = simulate(cfg500, road500, "passive")
    assert res500.info["substeps"] == 40
    res1k = simulate(CFG, road, "passive")
    # same physics at either tick: passive peak acceleration agrees
    assert res500.metrics["accel_peak_mps2"] == pytest.approx(
        res1k.metrics["accel_peak_mps2"], rel=0.02)



class _Scripted:
    """Force reference read from a fixed sequence (ignores the readings); raises its
    fault flag at tick ``fault_at``."""

    name = "scripted"

    def __init__(self, seq: np.ndarray, fault_at: int = -1) -> None:
        self.seq, self.fault_at = seq, fault_at
        self.reset()

    def reset(self) -> None:
        self.k = 0
        self._fault = False

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        self._fault = self.k == self.fault_at
        self.k += 1
        return float(self.seq[self.k - 1])

    @property
    def fault(self) -> bool:
        return self._fault


def _replay_pi(force_ref: np.ndarray, meas_force: np.ndarray,
               meas_rattlespace: np.ndarray) -> np.ndarray:
    pi = PIForceLoop.from_config(CFG)
    return np.array([pi.step(r, f, x) for r, f, x in zip(force_ref, meas_force,
                                                          meas_rattlespace, strict=True)])


@pytest.mark.parametrize("delay_point", ["spool", "force_ref"])
def test_delay_point_delays_exactly_what_it_names(delay_point: str) -> None:
    """The PI force loop sees the (delayed or not) reference and the measured force, and
    exactly d ticks pass between computing and applying, at either delay point."""
    road = make_road("bump", SPEED_25MPH, 0.8, DT)
    seq = 400.0 * np.sin(np.arange(road.n_ticks) * 0.05)
    d = 3
    tr = run_closed_loop(CFG, road, _Scripted(seq), delay_ticks=d,
                         delay_point=delay_point).traces
    fref, spool, computed = tr["force_ref_n"], tr["spool_cmd"], tr["spool_computed"]
    np.testing.assert_array_equal(computed, _replay_pi(fref, tr["meas_force_n"],
                                                       tr["meas_rattlespace_m"]))
    if delay_point == "spool":
        np.testing.assert_array_equal(fref, seq)
        np.testing.assert_array_equal(spool[d:], computed[:-d])
        assert np.all(spool[:d] == 0.0)
    else:
        np.testing.assert_array_equal(fref[d:], seq[:-d])
        assert np.all(fref[:d] == 0.0)
        np.testing.assert_array_equal(spool, computed)
    assert np.any(spool != 0.0)


def test_delay_points_agree_without_delay_and_differ_with_it() -> None:
    road = make_road("bump", SPEED_25MPH, 0.8, DT)
    seq = 400.0 * np.sin(np.arange(road.n_ticks) * 0.05)

    def run(point: str, d: int) -> dict[str, float]:
        m = run_closed_loop(CFG, road, _Scripted(seq), delay_ticks=d, delay_point=point).metrics
        m.pop("realtime_factor")
        return m

    assert run("spool", 0) == run("force_ref", 0)
    assert run("spool", 5)["force_rms_n"] != run("force_ref", 5)["force_rms_n"]
    with pytest.raises(ValueError, match="delay_point"):
        run_closed_loop(CFG, road, None, delay_point="valve")


def test_controller_fault_latches_safe_state() -> None:
    road = make_road("bump", SPEED_25MPH, 0.5, DT)
    ctrl = _Scripted(np.full(road.n_ticks, 300.0), fault_at=40)
    res = run_closed_loop(CFG, road, ctrl, delay_ticks=2)
    m, tr = res.metrics, res.traces
    assert m["n_faults"] == 1.0 and m["fault_time_s"] == pytest.approx(40 * DT)
    assert ctrl.k == 41                             # never asked again after the fault
    assert np.all(tr["force_ref_n"][40:] == 0.0) and np.all(tr["spool_computed"][40:] == 0.0)
    assert np.all(tr["spool_cmd"][42:] == 0.0) and np.all(tr["spool_cmd"][2:40] != 0.0)


def test_bank_controller_weights_traces_and_diagnostics() -> None:
    road = make_road("rough-course", SPEED_25MPH, 0.5, DT, seed=2)
    ctrl = BankController(cached_design(CFG), CFG, "fuzzy", 1, road)
    res = run_closed_loop(CFG, road, ctrl, record_weights=True)
    w = res.traces["firing_weight"]
    assert w.shape == (road.n_ticks, len(cached_design(CFG).model_names))
    assert res.traces["q"].shape == w.shape and np.all(np.isfinite(w))
    assert 0.0 <= res.metrics["no_rule_fired_fraction"] <= 1.0
    assert res.controller == "fuzzy" and res.weight_set == 1
    with pytest.raises(ValueError, match="blending"):
        BankController(cached_design(CFG), CFG, "skyhook", 1, road)

def test_observing_before_arming_runs_the_controller_with_the_valve_safe() -> None:
    """``observe_s``: the bank steps from the first reading (as the service does, armed
    or not) while the valve is safe, so up to arming the plant is the passive rig tick
    for tick; the metrics are the armed window's alone."""
    road = make_road("rough-course", SPEED_25MPH, 3.0, DT, seed=3)
    n_obs = round(1.0 / DT)
    passive = simulate(CFG, road, "passive", seed=3)
    armed_late = simulate(CFG, road, "fuzzy", 1, seed=3, observe_s=1.0)
    tr, ptr = armed_late.traces, passive.traces
    np.testing.assert_array_equal(tr["rattlespace_m"][:n_obs + 1],
                                  ptr["rattlespace_m"][:n_obs + 1])
    assert np.all(tr["force_ref_n"][:n_obs] == 0.0) and np.all(tr["spool_cmd"][:n_obs] == 0.0)
    assert np.any(tr["force_ref_n"][n_obs:] != 0.0)
    assert not np.array_equal(tr["rattlespace_m"], ptr["rattlespace_m"])
    assert armed_late.info["observe_s"] == pytest.approx(1.0)
    # the controller ran while observing: its estimate had settled before arming
    assert math.isfinite(tr["sprung_mass_est_kg"][n_obs - 1])
    # the metrics skip the observed second like settle_s does, for active and passive alike
    p_obs = simulate(CFG, road, "passive", seed=3, observe_s=1.0).metrics
    p_settle = simulate(CFG, road, "passive", seed=3, settle_s=1.0).metrics
    assert p_obs["absorbed_power"] == p_settle["absorbed_power"]
    assert p_obs["absorbed_power"] != passive.metrics["absorbed_power"]
    with pytest.raises(ValueError, match="observe_s"):
        simulate(CFG, road, "fuzzy", 1, observe_s=3.0)
    with pytest.raises(ValueError, match="observe_s"):
        simulate(CFG, road, "fuzzy", 1, observe_s=-1.0)


def test_sensor_fault_latches_safe_state() -> None:
    cfg = CFG.replace(sensors={"lvdt_range_m": 0.005})
    road = make_road("bump", SPEED_25MPH, 1.5, DT)
    res = simulate(cfg, road, "fuzzy", 1)
    assert res.metrics["n_faults"] == 1.0
    k = round(res.metrics["fault_time_s"] / DT)
    assert k > 0
    assert np.all(res.traces["spool_cmd"][k:] == 0.0)
    assert np.all(res.traces["force_ref_n"][k:] == 0.0)


def test_bump_stop_slam_is_unstable() -> None:
    cfg = CFG.replace(vehicle={"rattlespace_travel_m": 0.01})
    road = make_road("bump", SPEED_25MPH, 1.5, DT)
    assert simulate(cfg, road, "passive").metrics["unstable"] == 1.0


def test_bad_arguments() -> None:
    road = make_road("bump", SPEED_25MPH, 0.1, DT)
    with pytest.raises(ValueError, match="unknown controller"):
        simulate(CFG, road, "pid")
    with pytest.raises(ValueError, match="weight set"):
        simulate(CFG, road, "fuzzy", 3)
    with pytest.raises(ValueError, match="sampled"):
        simulate(CFG, make_road("bump", SPEED_25MPH, 0.1, 2e-3), "passive")


def test_skyhook_and_zero_force_by_name() -> None:
    """``simulate`` runs skyhook with its tuned gains and zero-force (bypass closed, force
    reference 0 through the same force loop: the zero-gain skyhook, bit for bit)."""
    from hil.sim.closed_loop import ZeroForceController
    from hil.sim.skyhook import DEFAULT_GAINS, SkyhookController, SkyhookGains

    road = make_road("rough-course", SPEED_25MPH, 1.0, DT, seed=4)
    sky = simulate(CFG, road, "skyhook", seed=2)
    want = run_closed_loop(CFG, road, SkyhookController(CFG, DEFAULT_GAINS), seed=2)
    assert sky.controller == "skyhook"
    np.testing.assert_array_equal(sky.traces["spool_cmd"], want.traces["spool_cmd"])
    zero = simulate(CFG, road, "zero-force", seed=2)
    ref = run_closed_loop(CFG, road, SkyhookController(CFG, SkyhookGains(0.0, 0.0, 0.0)),
                          seed=2)
    assert zero.controller == "zero-force"
    assert np.all(zero.traces["force_ref_n"] == 0.0)
    np.testing.assert_array_equal(zero.traces["spool_cmd"], ref.traces["spool_cmd"])
    assert np.any(zero.traces["spool_cmd"] != 0.0)        # the valve is driven, closed
    assert zero.metrics["n_faults"] == 0.0 and zero.metrics["force_rms_n"] > 0.0
    z = ZeroForceController()
    nan = SensorReading(math.nan, 0.0, 0.0, 0)
    assert z.step(nan, RigPlant(CFG)) == 0.0 and z.fault
    z.reset()
    assert not z.fault


def test_cli_json_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "--road", "bump", "--duration", "1", "--controller", "passive",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["unstable"] == 0.0 and "absorbed_power" in out
    assert main(["sim", "--road", "gravel", "--duration", "1"]) == 2
    assert "unknown road" in capsys.readouterr().err
    assert main(["sim", "--road", "bump", "--duration", "1", "--weights", "7"]) == 2
    # (not the bump: over it every active law, skyhook too, slams the stops; the exit
    # status says so, docs/design.md §12)
    assert main(["sim", "--road", "iso-B", "--duration", "0.5", "--controller", "all"]) == 0
    table = capsys.readouterr().out
    assert all(c in table for c in ("passive", "zero-force", "skyhook", "lqg", "fuzzy",
                                    "bayes", "moving"))
    assert main(["sim", "--road", "iso-B", "--duration", "0.5", "--observe", "0.5",
                 "--controller", "fuzzy"]) == 0
    assert "observed 0.5 s, armed 0.5 s" in capsys.readouterr().out
    assert main(["sim", "--duration", "1", "--observe", "-1"]) == 2
    assert "--observe" in capsys.readouterr().err
    for c in ("zero-force", "skyhook"):
        assert main(["sim", "--road", "rough-course", "--duration", "1", "--controller", c,
                     "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["n_faults"] == 0.0 and out["force_rms_n"] > 0.0
