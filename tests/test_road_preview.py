"""Road preview (controller/road_preview.py, docs/design.md §12): the predictor against
python-control's discretisation and simulation of the same quarter car (without force,
and with the load cell's force fading), the
kernel's edge cases, the runtime's travel-law call, the configuration's checks, and a
course run on the nonlinear rig."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import (
    ConfigError,
    default_config,
    layer_config,
    layer_grid,
)
from controller.plant import (
    linear_model,
    static_tire_deflection_m,
    tire_damping_ns_per_m,
    tire_secant_stiffness_n_per_m,
)
from controller.road_preview import cached_road_preview, predicted_peak_m, road_preview
from controller.runtime.bank import BankRuntime
from controller.runtime.kernels import I_PVCALL
from hil.sim.closed_loop import cached_design, simulate
from hil.sim.roads import make_road

# one trigger and no force (the fading force on every layer with CFG_F)
PREVIEW = {"preview_horizon_s": 0.15, "preview_trigger_m": 0.06, "preview_check_s": 0.01,
           "preview_trigger_inner_m": 0.0, "preview_force_decay_s": 0.0}
CFG = default_config().replace(design=PREVIEW)
PV = road_preview(CFG)
DECAY_S = 0.05
CFG_F = default_config().replace(design={**PREVIEW, "preview_force_decay_s": DECAY_S})
PV_F = road_preview(CFG_F)


def _reference_readings(layer: int, dx: np.ndarray, road_velocity: np.ndarray,
                        reading_m: float, force_n: float = 0.0,
                        decay_s: float = 0.0) -> np.ndarray:
    """The LVDT reading over the horizon by python-control: the model of the bank
    layer's rig (road velocity and actuator force in), zero-order-hold discretised by
    control.c2d and simulated by control.forced_response from dx with the force
    ``force_n`` fading by exp(-t / decay_s) (none when decay_s is 0), the measured
    reading's offset added."""
    cfg = layer_config(CFG, *layer_grid(CFG)[layer])
    x2 = static_tire_deflection_m(cfg)
    lm = linear_model(cfg.vehicle, tire_secant_stiffness_n_per_m(x2, cfg.tire),
                      tire_damping_ns_per_m(x2, cfg.tire))
    sys_d = control.c2d(control.ss(lm.A, np.column_stack([lm.B1, lm.B2]),
                                   [[1.0, -1.0, 0.0, 0.0]], [[0.0, 0.0]]),
                        cfg.sample_time_s, method="zoh")
    n = road_velocity.size
    t = np.arange(n + 1) * cfg.sample_time_s
    force = (np.zeros(n + 1) if decay_s == 0.0
             else force_n * np.exp(-t / decay_s))
    u = np.vstack([np.append(road_velocity, 0.0), force])
    resp = control.forced_response(sys_d, T=t, U=u, X0=dx)
    r = np.asarray(resp.outputs).ravel()
    return reading_m + (r - r[0])


def test_shapes_and_off() -> None:
    assert road_preview(default_config().replace(design={"preview_horizon_s": 0.0})) is None
    on = road_preview(default_config())                 # on by default: 200 ms, 20 checks
    assert on is not None and on.horizon_ticks == 200 and on.ticks.size == 20
    assert PV is not None
    assert PV.horizon_ticks == 150 and PV.ticks[0] == 10 and PV.ticks[-1] == 150
    layers = len(layer_grid(CFG))
    assert PV.rows.shape == (layers, 15, 4) and PV.impulse.shape == (layers, 150)
    assert PV.force_rows.shape == (layers, 15)
    odd = road_preview(default_config().replace(design={"preview_horizon_s": 0.105}))
    assert odd is not None and odd.ticks[-1] == 105     # the horizon itself is checked


def test_layer_triggers_edge_and_inside() -> None:
    """The trigger of a layer inside the grid in spring rate and damping is
    preview_trigger_inner_m, with the force; on that edge (a scale the smallest or
    largest of its key) preview_trigger_m without it; inner 0 keeps one trigger."""
    one_trigger = default_config().replace(design={"preview_trigger_inner_m": 0.0})
    pv0 = road_preview(one_trigger)
    assert pv0 is not None and (pv0.trigger_m == 0.055).all() and pv0.edge_trigger_m == 0.055
    assert (pv0.force_rows != 0.0).any(axis=1).all()     # the force on every layer
    cfg = default_config().replace(design={"preview_trigger_inner_m": 0.075})
    d = cfg.design
    edge_keys = (d.spring_rate_scales, d.damping_scales)
    pv = road_preview(cfg)
    assert pv is not None and pv.edge_trigger_m == 0.055
    for layer, scales in enumerate(layer_grid(cfg)):
        inside = all(min(k) < v < max(k) or len(k) == 1
                     for v, k in zip(scales[1:3], edge_keys, strict=True))
        assert pv.trigger_m[layer] == (0.075 if inside else 0.055), scales
        assert bool((pv.force_rows[layer] != 0.0).all()) == inside, scales
        if inside:
            np.testing.assert_array_equal(pv.force_rows[layer], pv0.force_rows[layer])
    assert int((pv.trigger_m == 0.075).sum()) == (
        len(d.sprung_mass_scales) * len(d.tire_stiffness_scales)) == 21
    one = default_config().replace(design={     # one layer: inside (no edge to pass)
        "preview_trigger_inner_m": 0.07, "sprung_mass_scales": [1.0],
        "spring_rate_scales": [1.0], "damping_scales": [1.0], "tire_stiffness_scales": [1.0]})
    assert road_preview(one).trigger_m.tolist() == [0.07]  # type: ignore[union-attr]


def test_check_takes_the_running_layers_trigger() -> None:
    """A predicted peak of 65 mm (a reading held there, no road, the estimate at rest)
    calls the travel law under one 55 mm trigger; under a 75 mm inner trigger it does
    not while the bank runs its nominal layer (inside the grid), once the layer is an
    estimate (preview_trust_ticks after a reset: before, the edge's 55 mm); the governed
    comfort set (weight set 2) keeps the 55 mm edge trigger."""
    base = default_config()
    centre = base.design.bump_stop_centre_lvdt_m
    ahead = np.zeros(road_preview(base).horizon_ticks)   # type: ignore[union-attr]
    calls = []
    for inner in (0.0, 0.075):
        cfg = base.replace(design={"preview_trigger_inner_m": inner})
        pv = road_preview(cfg)
        assert pv is not None
        rt = BankRuntime(cached_design(cfg), weight_set=0, cfg=cfg)
        assert layer_grid(cfg)[rt.mass_layer] == (1.0, 1.0, 1.0, 1.0)
        assert rt.preview_trust_ticks > 1000
        for _ in range(rt.preview_trust_ticks - 1):
            rt.step(centre, 0.0, 0.0)
        assert rt.check_road_preview(pv, centre + 0.065, 0.0, ahead, 0)   # not yet
        assert rt.preview_trust(pv) == "settling"
        rt.step(centre, 0.0, 0.0)
        assert layer_grid(cfg)[rt.mass_layer] == (1.0, 1.0, 1.0, 1.0)
        assert rt.preview_trust(pv) == ("inside" if inner else "edge")
        calls.append(rt.check_road_preview(pv, centre + 0.065, 0.0, ahead, 0))
        rt.reset()                                           # a reset: not trusted again
        assert rt.check_road_preview(pv, centre + 0.065, 0.0, ahead, 0)
    assert calls == [True, False]
    governed = BankRuntime(cached_design(cfg), weight_set=2, cfg=cfg)
    assert governed.governed
    for _ in range(governed.preview_trust_ticks):
        governed.step(centre, 0.0, 0.0)
    assert governed.check_road_preview(pv, centre + 0.065, 0.0, ahead, 0)
    assert governed.preview_trust(pv) == "governor"
    fixed = BankRuntime(cached_design(cfg), weight_set=1, cfg=cfg)
    assert fixed.preview_trust(pv) == "unused"


@pytest.mark.parametrize("weight_set", [0, 1, 2])
def test_step_previewed_is_the_check_then_the_step(weight_set: int) -> None:
    """BankRuntime.step_previewed (the loop's one compiled call with a live preview)
    gives the force, the call and the state of check_road_preview then step, to the
    bit: the travel schedule (weight set 0) through the trust time and a reset, a fixed
    weight set, and the governed comfort set; readings near the stops so that the
    check calls the travel law on some ticks and not on others."""
    cfg = default_config()
    pv = road_preview(cfg)
    assert pv is not None
    n = 5200                                # past the trust time (4801 ticks)
    road = make_road("rough-course", 11.176, n / 1000 + 0.3, cfg.sample_time_s, seed=1)
    ride = simulate(cfg, road, "passive", 1, seed=1).traces      # the passive rig's sensors
    reading, accel = ride["meas_rattlespace_m"], ride["meas_accel_mps2"]
    force = 400.0 * np.sin(2 * np.pi * 0.7 * ride["time_s"])   # a load cell's reading
    ring = np.ascontiguousarray(np.append(np.diff(ride["road_height_m"]) / cfg.sample_time_s,
                                          np.zeros(pv.horizon_ticks + 1)))
    apart = BankRuntime(cached_design(cfg), weight_set=weight_set, cfg=cfg)
    fused = BankRuntime(cached_design(cfg), weight_set=weight_set, cfg=cfg)
    calls = 0
    for k in range(n):
        if k == n - 100:                        # a reset: the edge's prediction again
            apart.reset()
            fused.reset()
        called = apart.check_road_preview(pv, reading[k], force[k], ring, k)
        u_apart = apart.step(reading[k], accel[k], force[k])
        u_fused = fused.step_previewed(pv, reading[k], accel[k], force[k], ring, k)
        assert (u_fused, fused.preview_called) == (u_apart, called), k
        calls += called
    np.testing.assert_array_equal(fused._fv, apart._fv)
    same = np.arange(fused._iv.size) != I_PVCALL     # the fused call's own read-out
    np.testing.assert_array_equal(fused._iv[same], apart._iv[same])
    if weight_set == 1:
        assert calls == 0                       # a fixed weight set takes no preview
    else:
        assert 0 < calls < n - 500, calls


@settings(max_examples=30, deadline=None)
@given(layer=st.integers(0, len(layer_grid(CFG)) - 1),
       dx=st.lists(st.floats(-0.05, 0.05), min_size=4, max_size=4),
       velocity=st.lists(st.floats(-2.0, 2.0), min_size=150, max_size=150),
       reading=st.floats(-0.08, 0.08))
def test_peak_is_the_reference_prediction(layer: int, dx: list[float],
                                          velocity: list[float], reading: float) -> None:
    assert PV is not None
    x = np.array([*dx[:2], 10.0 * dx[2], 10.0 * dx[3]])        # velocities up to 0.5 m/s
    w = np.array(velocity)
    ref = _reference_readings(layer, x, w, reading)
    want = max(abs(reading), *(abs(ref[j]) for j in PV.ticks))
    got = predicted_peak_m(PV.rows, PV.ticks, PV.impulse, PV.force_rows, layer, x, 0.0,
                           reading, 0.0, w, 0)
    assert got == pytest.approx(want, rel=1e-9, abs=1e-12)
    # design.preview_force_decay_s 0: the load cell's force is left out
    assert not PV.force_rows.any()
    assert predicted_peak_m(PV.rows, PV.ticks, PV.impulse, PV.force_rows, layer, x, 3e3,
                            reading, 0.0, w, 0) == got


@settings(max_examples=30, deadline=None)
@given(layer=st.integers(0, len(layer_grid(CFG)) - 1),
       dx=st.lists(st.floats(-0.05, 0.05), min_size=4, max_size=4),
       velocity=st.lists(st.floats(-2.0, 2.0), min_size=150, max_size=150),
       force=st.floats(-8e3, 8e3), reading=st.floats(-0.08, 0.08))
def test_peak_with_the_fading_force_is_the_reference_prediction(
        layer: int, dx: list[float], velocity: list[float], force: float,
        reading: float) -> None:
    """design.preview_force_decay_s > 0: the load cell's force, fading, as an input of
    python-control's simulation of the same model."""
    assert PV_F is not None
    x = np.array([*dx[:2], 10.0 * dx[2], 10.0 * dx[3]])
    w = np.array(velocity)
    ref = _reference_readings(layer, x, w, reading, force, DECAY_S)
    want = max(abs(reading), *(abs(ref[j]) for j in PV_F.ticks))
    got = predicted_peak_m(PV_F.rows, PV_F.ticks, PV_F.impulse, PV_F.force_rows, layer, x,
                           force, reading, 0.0, w, 0)
    assert got == pytest.approx(want, rel=1e-9, abs=1e-12)


def _plain_peak(rows: np.ndarray, ticks: np.ndarray, impulse: np.ndarray,
                force_rows: np.ndarray, layer: int, dx: np.ndarray, force: float,
                reading: float, centre: float, w: np.ndarray, start: int) -> float:
    """The kernel's sums one look-ahead tick after the other, in plain Python."""
    peak = abs(reading - centre)
    for p, j in enumerate(ticks):
        r = reading - centre + float(force_rows[layer, p]) * force
        for s in range(4):
            r += float(rows[layer, p, s]) * float(dx[s])
        for i in range(min(int(j), w.size - start)):
            r += float(impulse[layer, j - 1 - i]) * float(w[start + i])
        if math.isnan(r):
            return math.nan
        peak = max(peak, abs(r))
    return peak


@settings(max_examples=40, deadline=None)
@given(layer=st.integers(0, len(layer_grid(CFG)) - 1), n_ticks=st.integers(1, 15),
       window=st.integers(0, 160), seed=st.integers(0, 2**32 - 1))
def test_kernel_sums_bit_for_bit_as_the_plain_sum(layer: int, n_ticks: int, window: int,
                                                  seed: int) -> None:
    """The kernel sums four look-ahead ticks side by side: the same bits as summing them
    one after the other, for any number of look-ahead ticks and any window length."""
    assert PV is not None
    rng = np.random.default_rng(seed)
    assert PV_F is not None
    ticks = np.ascontiguousarray(PV_F.ticks[:n_ticks])
    rows = np.ascontiguousarray(PV_F.rows[:, :n_ticks])
    force_rows = np.ascontiguousarray(PV_F.force_rows[:, :n_ticks])
    dx = rng.normal(0.0, 0.02, 4)
    w = rng.normal(0.0, 0.5, window + 3)
    reading = float(rng.normal(0.0, 0.02))
    force = float(rng.normal(0.0, 2e3))
    args = (rows, ticks, PV_F.impulse, force_rows, layer, dx, force, reading, 0.001, w, 3)
    assert predicted_peak_m(*args) == _plain_peak(*args)


def test_kernel_edges() -> None:
    assert PV is not None
    zeros = np.zeros(4)
    w = np.full(150, 0.3)
    layer = len(layer_grid(CFG)) // 2
    args = (PV.rows, PV.ticks, PV.impulse, PV.force_rows, layer)
    # at rest on a flat road: the reading itself, measured from the stops' centre
    assert predicted_peak_m(*args, zeros, 0.0, 0.02, 0.005, np.zeros(150),
                            0) == pytest.approx(0.015)
    # a short window: the missing road counts as 0 (the end of a recorded road)
    short = predicted_peak_m(*args, zeros, 0.0, 0.0, 0.0, w[:20], 0)
    padded = predicted_peak_m(*args, zeros, 0.0, 0.0, 0.0, np.append(w[:20], np.zeros(130)),
                              0)
    assert short == padded > 0.0
    # the window starts at ``start`` of the array, without a copy (the loop's ring)
    assert predicted_peak_m(*args, zeros, 0.0, 0.0, 0.0, np.append(np.full(7, 5.0), w[:20]),
                            7) == short
    # a rising road compresses the suspension: the prediction grows with the velocity
    assert predicted_peak_m(*args, zeros, 0.0, 0.0, 0.0, 2.0 * w, 0) > short
    for bad in ((np.full(4, math.nan), 0.0, w), (zeros, math.nan, w),
                (zeros, 0.0, np.full(150, math.nan))):
        assert math.isnan(predicted_peak_m(*args, bad[0], 0.0, bad[1], 0.0, bad[2], 0))
    # the load cell's force: a force that extends the actuator (pushes the body up)
    # opens the rattlespace (reading x1 - x2 < 0), more the longer it is held
    assert PV_F is not None
    args_f = (PV_F.rows, PV_F.ticks, PV_F.impulse, PV_F.force_rows, layer, zeros)
    rest = predicted_peak_m(*args_f, 0.0, 0.0, 0.0, np.zeros(150), 0)
    pushed = predicted_peak_m(*args_f, 2e3, 0.0, 0.0, np.zeros(150), 0)
    assert rest == 0.0 < pushed
    assert (PV_F.force_rows < 0.0).all()
    held = road_preview(CFG.replace(design={"preview_force_decay_s": 10.0}))
    assert held is not None and (held.force_rows < PV_F.force_rows).all()
    assert math.isnan(predicted_peak_m(*args_f, math.nan, 0.0, 0.0, np.zeros(150), 0))


def test_travel_law_call_sets_the_travel_law_for_the_next_step() -> None:
    design = cached_design(CFG)
    rt = BankRuntime(design, weight_set=0, cfg=CFG)
    rt.step(0.0, 0.0, 0.0)
    assert rt.comfort_share == 1.0           # quiet: the comfort law alone
    rt.call_travel_law()
    rt.step(0.0, 0.0, 0.0)
    assert rt.comfort_share == 0.0
    assert rt.schedule_usage_m == pytest.approx(CFG.design.schedule_full_m)
    for _ in range(1500):                    # then the usual release (0.55 s here)
        rt.step(0.0, 0.0, 0.0)
    assert rt.comfort_share == 1.0
    fixed = BankRuntime(design, weight_set=1, cfg=CFG)     # the travel set, alone
    fixed.call_travel_law()
    fixed.step(0.0, 0.0, 0.0)
    assert fixed.schedule_usage_m == 0.0 and fixed.comfort_share == 0.0
    ahead = np.full(PV.horizon_ticks, math.nan)    # a NaN prediction calls where it can
    assert not fixed.check_road_preview(PV, 0.0, 0.0, ahead, 0)
    governed = BankRuntime(design, weight_set=2, cfg=CFG)  # weight set 2: governed
    assert governed.check_road_preview(PV, 0.0, 0.0, ahead, 0)
    governed.step(0.0, 0.0, 0.0)
    assert governed.comfort_share == 0.0
    assert governed.schedule_usage_m == pytest.approx(CFG.design.governor_full_m)


def test_configuration_checks_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"design\.preview_horizon_s"):
        default_config().replace(design={"preview_horizon_s": 0.1, "schedule_release_s": 0.0})
    with pytest.raises(ConfigError, match=r"design\.preview_check_s"):
        default_config().replace(design={"preview_horizon_s": 0.01, "preview_check_s": 0.02,
                                         "preview_clamp_horizon_s": 0.01})
    with pytest.raises(ConfigError, match=r"design\.preview_clamp_horizon_s"):
        default_config().replace(design={"preview_clamp_horizon_s": 0.3})   # > horizon
    with pytest.raises(ConfigError, match=r"design\.preview_clamp_horizon_s"):
        default_config().replace(design={"preview_horizon_s": 1.0,
                                         "preview_clamp_horizon_s": 0.3})  # > 255 ticks
    with pytest.raises(ConfigError, match=r"design\.preview_trigger_m"):
        default_config().replace(design={"preview_trigger_m": 0.0})
    with pytest.raises(ConfigError, match=r"design\.preview_schedule_full_m"):
        default_config().replace(design={"preview_schedule_start_m": 0.2,
                                         "preview_schedule_full_m": 0.1})


def test_runtime_switches_the_schedule_for_a_live_preview() -> None:
    """use_preview_schedule swaps the schedule's thresholds (the envelope carries over):
    at 40 mm of usage the reading-only schedule (25 / 55 mm) gives the travel law part
    of the force, the preview's (50 / 80 mm) none; call_travel_law reaches the running
    schedule's full usage either way."""
    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design

    cfg = default_config()
    rt = BankRuntime(cached_design(cfg), weight_set=0, cfg=cfg)
    centre = cfg.design.bump_stop_centre_lvdt_m
    shares = []
    for live in (False, True):
        rt.reset()
        rt.use_preview_schedule(live)
        assert rt.preview_schedule is live
        for _ in range(3):
            rt.step(centre + 0.04, 0.0, 0.0)
        shares.append(rt.comfort_share)
        rt.call_travel_law()
        rt.step(centre, 0.0, 0.0)
        full = (cfg.design.preview_schedule_full_m if live else cfg.design.schedule_full_m)
        assert rt.schedule_usage_m >= full - 1e-12
        assert rt.comfort_share == 0.0
    assert 0.0 < shares[0] < 1.0 and shares[1] == 1.0


def test_course_run_with_the_preview() -> None:
    """The default law on the thesis course, road seed 7: with the road preview the
    comfort set runs alone except where the preview calls the travel law.  Against the
    comfort set alone (no preview, the reading's thresholds out of the way, the
    stop-contact monitor degrading it) and against the schedule on the reading alone (no
    preview, as on a rig that sends no RoadPreview): less absorbed power than either, no
    slam, no fault, stop contact within passive's + 0.1 % of the run."""
    cfg = default_config()
    seed = 7
    road = make_road("rough-course", 11.176, 60.0, cfg.sample_time_s, seed)
    passive = simulate(cfg, road, "passive", 0, seed=seed).metrics
    with_preview = simulate(cfg, road, "fuzzy", 0, seed=seed).metrics
    comfort = simulate(cfg.replace(design={"preview_horizon_s": 0.0,
                                           "schedule_start_m": 0.5, "schedule_full_m": 1.0}),
                       road, "fuzzy", 0, seed=seed).metrics
    reading = simulate(cfg.replace(design={"preview_horizon_s": 0.0}), road, "fuzzy", 0,
                       seed=seed).metrics
    assert with_preview["n_faults"] == 0 and not with_preview["bump_stop_slam"]
    assert with_preview["bump_stop_time_s"] <= passive["bump_stop_time_s"] + 0.001 * 60.0
    assert 0.0 < with_preview["preview_call_fraction"] < 0.1
    assert comfort["preview_call_fraction"] == reading["preview_call_fraction"] == 0.0
    assert with_preview["absorbed_power"] < 0.7 * comfort["absorbed_power"]
    assert with_preview["absorbed_power"] < 0.95 * reading["absorbed_power"]


def test_simulator_calls_the_travel_law_on_a_nonfinite_prediction() -> None:
    """The simulator's preview: a road whose velocity ahead is not finite gives a NaN
    prediction, which calls the travel law (the conservative side); the same road at
    rest ahead calls nothing."""
    import dataclasses

    from hil.sim.closed_loop import BankController
    from hil.sim.sensors import SensorReading
    cfg = default_config()
    flat = make_road("flat", 11.176, 1.0, cfg.sample_time_s)
    velocity = flat.velocity_mps.copy()
    velocity[100:] = math.nan                # inside the first tick's window
    bad = dataclasses.replace(flat, velocity_mps=velocity)
    reading = SensorReading(0.0, 0.0, 0.0, 0)
    for road, calls, share in ((flat, 0, 1.0), (bad, 1, 0.0)):
        ctrl = BankController(cached_design(cfg), cfg, "fuzzy", 0, road)
        ctrl.step(reading, None)  # type: ignore[arg-type]   # the plant is not read
        assert ctrl.preview_calls == calls
        assert ctrl.rt.comfort_share == share


def test_one_predictor_per_configuration_is_shared() -> None:
    """The runtime's road-at-rest clamp and every other user of one configuration take
    the same predictor object (built once per process), equal to a fresh one; another
    design configuration gets its own."""
    shared = cached_road_preview(CFG)
    assert shared is not None and cached_road_preview(CFG) is shared
    fresh = road_preview(CFG)
    assert fresh is not None
    np.testing.assert_array_equal(shared.brake_rows, fresh.brake_rows)
    np.testing.assert_array_equal(shared.rows, fresh.rows)
    assert BankRuntime(cached_design(CFG), cfg=CFG)._at_rest is shared
    other = cached_road_preview(CFG_F)
    assert other is not None and other is not shared
