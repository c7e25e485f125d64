"""The road preview's stop clamp (``design.preview_stop_clamp_m``, docs/design.md §12):
its force bounds against python-control's simulation of the same quarter car (with the
bound force, the prediction stays inside the clamp distance), the clip, the trust in its
own predictions and the airborne gate, and runs on the nonlinear rig: the single bump
that every law slammed is now no worse than passive, with or without a live preview,
and a bank on the wrong layer does not clamp."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import ConfigError, default_config, layer_config, layer_grid, one_layer
from controller.plant import (
    linear_model,
    static_tire_deflection_m,
    tire_damping_ns_per_m,
    tire_secant_stiffness_n_per_m,
)
from controller.road_preview import clamp_force_bounds_n, road_preview
from controller.runtime.bank import CLAMP_AIRBORNE_WEIGHT, BankRuntime, preview_clamp
from controller.runtime.kernels import (
    F_AUTH,
    F_PVC_AIRW,
    F_PVC_BRAKE,
    F_PVC_FMAX,
    F_PVC_FMIN,
    F_PVC_MS,
    F_PVC_TRUST2,
    F_TS,
    I_PVCLAMP,
    I_PVCLAMP_TICKS,
)
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop, simulate
from hil.sim.plant import RigPlant
from hil.sim.roads import make_road
from hil.sim.sensors import SensorReading

CFG = default_config()
PV = road_preview(CFG)
assert PV is not None
CENTRE = CFG.design.bump_stop_centre_lvdt_m


def _reference(layer: int, dx: np.ndarray, road_velocity: np.ndarray,
               force_n: float = 0.0) -> np.ndarray:
    """The change of the LVDT reading over the horizon, by python-control: the layer's
    rig zero-order-hold discretised (control.c2d) and simulated (control.forced_response)
    from the deviation dx, with the road velocity and a force reference ``force_n``
    held from the next tick on, delivered through a first-order lag of half
    ``design.stop_barrier_lag_s``."""
    cfg = layer_config(CFG, *layer_grid(CFG)[layer])
    x2 = static_tire_deflection_m(cfg)
    lm = linear_model(cfg.vehicle, tire_secant_stiffness_n_per_m(x2, cfg.tire),
                      tire_damping_ns_per_m(x2, cfg.tire))
    sys_d = control.c2d(control.ss(lm.A, np.column_stack([lm.B1, lm.B2]), [[1.0, -1.0, 0.0, 0.0]],
                                   [[0.0, 0.0]]), cfg.sample_time_s, method="zoh")
    n = road_velocity.size
    dt = cfg.sample_time_s
    delivered = force_n * (1.0 - np.exp(-dt * np.arange(1, n + 2)
                                        / (0.5 * cfg.design.stop_barrier_lag_s)))
    resp = control.forced_response(sys_d, T=np.arange(n + 1) * dt,
                                   U=np.vstack([np.append(road_velocity, 0.0), delivered]),
                                   X0=dx)
    r = np.asarray(resp.outputs).ravel()
    return r - r[0]


def test_the_clamp_looks_50_ms_ahead_by_default() -> None:
    assert PV is not None and PV.clamp_m == 0.08 and PV.clamp_points == 5
    assert PV.ticks[PV.clamp_points - 1] == 50
    off = road_preview(CFG.replace(design={"preview_stop_clamp_m": 0.0}))
    assert off is not None and off.clamp_points == 0
    short = road_preview(CFG.replace(design={"preview_clamp_horizon_s": 0.004}))
    assert short is not None and short.clamp_points == 1     # at least the first check
    with pytest.raises(ConfigError, match=r"design\.preview_clamp_trust_m"):
        CFG.replace(design={"preview_clamp_trust_m": 0.0})
    # the clamp looks at least one check ahead: a check spacing beyond its ring is refused
    wide = {"preview_horizon_s": 0.5, "preview_check_s": 0.3}
    with pytest.raises(ConfigError, match=r"design\.preview_check_s"):
        CFG.replace(design=wide)
    assert CFG.replace(design={**wide, "preview_stop_clamp_m": 0.0}).design.preview_check_s == 0.3


@settings(max_examples=25, deadline=None)
@given(layer=st.integers(0, len(layer_grid(CFG)) - 1),
       dx=st.lists(st.floats(-0.02, 0.02), min_size=4, max_size=4),
       velocity=st.lists(st.floats(-1.0, 1.0), min_size=1, max_size=8),
       reading=st.floats(-0.07, 0.07), points=st.integers(1, 8),
       brake_n=st.sampled_from([0.0, 2000.0, 8000.0]))
def test_the_bound_force_keeps_the_prediction_inside(
        layer: int, dx: list[float], velocity: list[float], reading: float,
        points: int, brake_n: float) -> None:
    """With the least (greatest) force of the bounds held, python-control's simulation of
    the layer's rig from dx with the road velocity ahead stays within the clamp distance
    of the compression (rebound) stop at every look-ahead tick checked, and touches it
    at one, unless the bound is the braking limit (then the prediction beyond reaches
    no further than the no-force one) or no tick bounds it (the no-force prediction
    then never reaches the stop); the last value is the no-force prediction."""
    assert PV is not None
    w = np.repeat(np.asarray(velocity), -(-PV.horizon_ticks // len(velocity)))
    w = np.ascontiguousarray(w[:PV.horizon_ticks])
    x = np.asarray(dx)
    clamp = PV.clamp_m
    f_min, f_max, last = clamp_force_bounds_n(PV.rows, PV.ticks, PV.impulse, PV.brake_rows,
                                              layer, x, CENTRE + reading, CENTRE, w, 0,
                                              points, clamp, brake_n)
    at = PV.ticks[:min(points, PV.ticks.size)]
    free = reading + _reference(layer, x, w)[at]
    assert last == pytest.approx(free[-1], abs=1e-9)
    assert f_min <= brake_n and f_max >= -brake_n
    for bound, sign in ((f_min, 1.0), (f_max, -1.0)):
        if math.isinf(bound):
            assert sign * bound < 0 and (sign * free < clamp).all()
            continue
        held = reading + _reference(layer, x, w, bound)[at]
        if sign * bound < brake_n:
            assert (sign * held <= clamp + 1e-9).all()
            assert (sign * held).max() == pytest.approx(clamp, abs=1e-9)
        else:                               # braking limited: as far as it gets
            assert (sign * held <= sign * free + 1e-12).all()


def test_nan_in_zero_force_out() -> None:
    assert PV is not None
    w = np.zeros(PV.horizon_ticks)
    f_min, f_max, last = clamp_force_bounds_n(PV.rows, PV.ticks, PV.impulse, PV.brake_rows,
                                              0, np.zeros(4), np.nan, CENTRE, w, 0,
                                              PV.clamp_points, PV.clamp_m, 4000.0)
    assert (f_min, f_max) == (0.0, 0.0) and np.isnan(last)


@pytest.mark.parametrize(("bounds", "force", "out"), [
    ((-math.inf, math.inf), -500.0, -500.0),
    ((0.0, math.inf), -500.0, 0.0), ((0.0, math.inf), 500.0, 500.0),
    ((1500.0, math.inf), 500.0, 1500.0),            # braking from the compression stop
    ((-300.0, math.inf), -500.0, -300.0),            # a push toward it, limited
    ((-math.inf, 0.0), 500.0, 0.0), ((-math.inf, -800.0), -500.0, -800.0),
    ((100.0, -100.0), 500.0, 0.0), ((0.0, math.inf), 0.0, 0.0)])
def test_clip_to_the_bounds(bounds: tuple[float, float], force: float, out: float) -> None:
    fv = np.zeros(F_PVC_FMAX + 1)
    fv[F_PVC_FMIN], fv[F_PVC_FMAX] = bounds
    iv = np.zeros(I_PVCLAMP_TICKS + 1, dtype=np.int64)
    assert preview_clamp(fv, iv, force) == out
    assert iv[I_PVCLAMP_TICKS] == int(out != force)


def _checked(rt: BankRuntime, reading_m: float, trusted: bool = True,
             airborne_weight: float = 0.0) -> tuple[float, float] | None:
    """The clamp's force bounds after a check at a held reading (road at rest), None
    when it does not act."""
    assert PV is not None
    rt._fv[F_PVC_MS] = 0.0 if trusted else 4.0 * rt._fv[F_PVC_TRUST2]
    rt._fv[F_PVC_AIRW] = airborne_weight
    rt.check_road_preview(PV, reading_m, 0.0, np.zeros(PV.horizon_ticks), 0)
    if not rt._iv[I_PVCLAMP]:
        return None
    return float(rt._fv[F_PVC_FMIN]), float(rt._fv[F_PVC_FMAX])


@pytest.mark.parametrize("weight_set", [0, 1, 2])
def test_check_bounds_the_force_toward_the_stop_the_prediction_reaches(
        weight_set: int) -> None:
    """A reading held 85 mm toward a stop (the estimate at rest, no road) is beyond the
    80 mm clamp: braking away from that stop up to the barrier's braking force
    (``preview_clamp_brake``; off: no push toward it), for every weight set; 40 mm only
    limits the push toward either stop; untrusted, or with the airborne model in the
    blend, no clamp; the step after the check is within the bounds and clears them."""
    rt = BankRuntime(cached_design(CFG), weight_set=weight_set, cfg=CFG)
    centre = float(rt._fv[F_TS])
    assert centre == CENTRE
    brake = float(rt._fv[F_PVC_BRAKE])
    assert brake == 4000.0                          # half the 8 kN force limit
    limit = CFG.force_loop.force_limit_n
    lo, hi = _checked(rt, centre + 0.085) or (math.nan, math.nan)
    assert lo == brake and hi > limit              # the far stop bounds nothing
    lo, hi = _checked(rt, centre - 0.085) or (math.nan, math.nan)
    assert hi == -brake and lo < -limit
    rt._fv[F_AUTH] = 0.25                           # a degrading estimator brakes less
    assert (_checked(rt, centre + 0.085) or (math.nan,))[0] == 0.25 * brake
    rt._fv[F_AUTH] = 1.0
    no_brake = CFG.replace(design={"preview_clamp_brake": False})
    rt_nb = BankRuntime(cached_design(no_brake), weight_set=weight_set, cfg=no_brake)
    assert (_checked(rt_nb, centre + 0.085) or (math.nan,))[0] == 0.0
    lo, hi = _checked(rt, centre + 0.04) or (math.nan, math.nan)
    assert -limit < lo < -1000.0 and hi > limit     # a push toward the near stop, limited
    assert _checked(rt, centre + 0.085, trusted=False) is None
    assert _checked(rt, centre + 0.085, airborne_weight=2 * CLAMP_AIRBORNE_WEIGHT) is None
    assert _checked(rt, centre + 0.085, airborne_weight=CLAMP_AIRBORNE_WEIGHT) is not None
    for reading, sign in ((centre + 0.085, -1.0), (centre - 0.085, 1.0)):
        before = rt.preview_clamp_ticks
        _checked(rt, reading)
        u = rt.step(reading, 0.0, 0.0)
        assert sign * u <= -brake               # braking away from the stop
        assert rt.preview_clamp_ticks - before in (0, 1)
        assert rt._iv[I_PVCLAMP] == 0           # for that step only
    off = CFG.replace(design={"preview_stop_clamp_m": 0.0})
    rt_off = BankRuntime(cached_design(off), weight_set=weight_set, cfg=off)
    pv_off = road_preview(off)
    assert pv_off is not None
    rt_off._fv[F_PVC_MS] = 0.0
    rt_off.check_road_preview(pv_off, centre + 0.085, 0.0, np.zeros(pv_off.horizon_ticks), 0)
    assert rt_off._iv[I_PVCLAMP] == 0


def test_trust_comes_with_predictions_that_come_true() -> None:
    """From a reset the clamp is not trusted; with the rig at rest its 50 ms
    predictions come true, and it is trusted within half a second; a reading that jumps
    away from every prediction (the estimate no longer fits) takes the trust away."""
    assert PV is not None
    rt = BankRuntime(cached_design(CFG), weight_set=1, cfg=CFG)
    ring = np.zeros(PV.horizon_ticks + 1000)
    trust2 = float(rt._fv[F_PVC_TRUST2])
    assert not rt._fv[F_PVC_MS] < trust2
    for k in range(500):
        rt.step_previewed(PV, CENTRE, 0.0, 0.0, ring, k)
    assert rt._fv[F_PVC_MS] < 0.5 * trust2
    for k in range(500, 700):               # the reading 0.1 m off every prediction
        rt.step_previewed(PV, CENTRE + (0.1 if k % 2 else -0.1), 0.0, 0.0, ring, k)
        rt._iv[I_PVCLAMP] = 0
    assert not rt._fv[F_PVC_MS] < trust2


@pytest.mark.parametrize("speed_mps", [10.0, 11.176, 15.0])
def test_single_bump_no_worse_than_passive(speed_mps: float) -> None:
    """The single 80 mm bump, which every active law slammed (93-94 mm at 10-11 m/s,
    passive 86.6-87.6 mm): with the clamp no law slams and the peak is within 1 mm of
    passive's; with the clamp off the fuzzy law slams (the case it is for)."""
    road = make_road("bump", speed_mps, 1.5, CFG.sample_time_s, 1)
    passive = simulate(CFG, road, "passive", seed=1).metrics
    assert passive["bump_stop_slam"] == 0.0
    for mode in ("fuzzy", "lqg"):
        m = simulate(CFG, road, mode, 0, seed=1).metrics
        assert m["bump_stop_slam"] == 0.0 and m["n_faults"] == 0.0, mode
        assert m["rattlespace_peak_m"] <= passive["rattlespace_peak_m"] + 0.001, mode
        assert m["preview_clamp_fraction"] > 0.0
    if speed_mps < 15.0:
        off = simulate(CFG.replace(design={"preview_stop_clamp_m": 0.0}), road, "fuzzy", 0,
                       seed=1).metrics
        assert off["bump_stop_slam"] == 1.0


@pytest.mark.parametrize("speed_mps", [10.0, 11.176, 15.0])
def test_single_bump_without_a_preview_stays_off_the_stops(speed_mps: float) -> None:
    """A rig that sends no road preview (``[emulator] road_preview_s = 0``): the clamp on
    the road-at-rest prediction brakes the bump's approach, so no law slams and the peak
    stays below passive's (84-85 mm against 86.6-88.3 mm); without that clamp every law
    slams (92-93 mm)."""
    road = make_road("bump", speed_mps, 1.5, CFG.sample_time_s, 1)
    blind = CFG.replace(emulator={"road_preview_s": 0.0})
    passive = simulate(blind, road, "passive", seed=1).metrics
    for mode in ("fuzzy", "lqg"):
        m = simulate(blind, road, mode, 0, seed=1).metrics
        assert m["bump_stop_slam"] == 0.0 and m["n_faults"] == 0.0, mode
        assert m["rattlespace_peak_m"] < passive["rattlespace_peak_m"], mode
        assert m["preview_clamp_fraction"] > 0.0 and m["preview_call_fraction"] == 0.0
    off = simulate(blind.replace(design={"stop_clamp_road_at_rest": False}), road, "fuzzy",
                   0, seed=1).metrics
    assert off["bump_stop_slam"] == 1.0 and off["preview_clamp_fraction"] == 0.0


class _TrustTrace(BankController):
    """The bank with the clamp's mean-square prediction error [m^2] of every tick."""

    def reset(self) -> None:
        super().reset()
        self.ms: list[float] = []

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        u = super().step(reading, plant)
        self.ms.append(float(self.rt._fv[F_PVC_MS]))
        return u


def test_a_bank_on_the_wrong_layer_does_not_clamp() -> None:
    """A plant of 0.7 x the configured sprung mass under a bank of three mass layers
    (0.7, 1.0, 1.3) on the configured spring, damper and tire: until the bank has moved
    to its layer (about 3 s) the nominal layer's estimate drifts, its 50 ms prediction
    misses the reading by decimetres, and the clamp does not trust it (nor does the
    airborne gate pass it: the airborne model takes weight); on its layer the
    predictions come true again.  Not one tick is clipped."""
    road = make_road("rough-course", 11.176, 6.0, CFG.sample_time_s, 1)
    light = one_layer(CFG).replace(design={"sprung_mass_scales": [0.7, 1.0, 1.3]})
    ctrl = _TrustTrace(cached_design(light), light, "fuzzy", 1, road)
    res = run_closed_loop(light.replace(emulator={"sprung_mass_scale": 0.7}), road, ctrl,
                          seed=1)
    trust2 = light.design.preview_clamp_trust_m ** 2
    ms = np.asarray(ctrl.ms)
    assert ms[500:2500].max() > 10.0 * trust2           # the prediction drifted
    assert ctrl.rt.mass_layer == 0 and ms[-1000:].max() < trust2
    assert res.metrics["preview_clamp_fraction"] == 0.0 and res.metrics["n_faults"] == 0.0
