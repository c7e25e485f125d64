"""End-stop barrier (controller/stop_barrier.py, docs/design.md §9.7): the numba kernel
against the plain-Python law, the law's invariants, forward invariance on its design
model, and the weight-set-2 runs on the nonlinear rig it exists for."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import ConfigError, default_config
from controller.runtime.kernels import (
    F_BS_HI,
    F_BS_LO,
    F_FFB,
    F_FFW,
    F_SB,
    F_SB_DF,
    F_SB_V,
    FV_HEAD,
    I_SB_TICKS,
    IV_HEAD,
    stop_barrier,
)
from controller.stop_barrier import (
    BARRIER_SIZE,
    StopBarrier,
    barrier_force,
    force_bound_toward_stop,
)
from controller.stop_barrier import stop_barrier as barrier_of
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop, simulate
from hil.sim.montecarlo import draw_params
from hil.sim.plant import RigPlant
from hil.sim.roads import make_road
from hil.sim.sensors import SensorReading

LO, HI = -0.08, 0.08
ON = {"stop_barrier": True}


def _barrier(**kw: float) -> StopBarrier:
    cfg = default_config().replace(design={**ON, **kw})
    return barrier_of(cfg, 10342.5, 8000.0)


def _kernel(u: float, r: float, rate: float, b: StopBarrier) -> tuple[float, float, int]:
    """The kernel with its rate filters bypassed: F_FFB = 0 so the LVDT rate is F_FFW,
    and the barrier's own low-pass starts at that rate."""
    fv = np.zeros(FV_HEAD)
    iv = np.zeros(IV_HEAD, dtype=np.int64)
    fv[F_BS_LO], fv[F_BS_HI] = LO, HI
    fv[F_SB:F_SB + BARRIER_SIZE] = b.as_array()
    fv[F_FFB], fv[F_FFW], fv[F_SB_V] = 0.0, rate, math.nan
    out = stop_barrier(fv, iv, u, r)
    return out, float(fv[F_SB_DF]), int(iv[I_SB_TICKS])


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e4, 1e4), st.floats(-0.12, 0.12), st.floats(-2.0, 2.0))
def test_kernel_is_the_law_and_never_pushes_toward_a_stop(u: float, r: float,
                                                          rate: float) -> None:
    b = _barrier()
    out, df, n = _kernel(u, r, rate, b)
    ref = barrier_force(u, r, rate, LO, HI, b)
    assert out == pytest.approx(ref, rel=1e-12, abs=1e-9)
    assert df == pytest.approx(out - u, rel=1e-12, abs=1e-9) and n == int(out != u)
    passive = b.stiffness_n_per_m * r + b.damping_ns_per_m * rate
    u_hi, h_hi = force_bound_toward_stop(HI - r, rate, -passive, b)
    u_lo, h_lo = force_bound_toward_stop(r - LO, -rate, passive, b)
    if -u_hi <= u <= u_lo:                       # safe: the law is untouched
        assert out == u
    if -u_hi <= u_lo:                            # else the nearer stop's bound
        assert out == min(max(u, -u_hi), u_lo)
    else:
        assert out == (-u_hi if h_hi <= h_lo else u_lo)
    # a change is only ever away from a stop whose bound the law's force broke
    if out > u:         # more extension: the law pushed past the compression bound
        assert u < -u_hi
    if out < u:         # more compression: the law pushed past the rebound bound
        assert u > u_lo
    # it never asks for more than the braking force away from a stop
    assert u_hi >= -b.braking_force_n and u_lo >= -b.braking_force_n


def test_barrier_off_is_the_identity() -> None:
    b = barrier_of(default_config(), 10342.5, 8000.0)
    assert b.mass_kg == 0.0
    out, df, n = _kernel(-5000.0, 0.079, 1.0, b)
    assert (out, df, n) == (-5000.0, 0.0, 0)


@pytest.mark.parametrize(("key", "value"), [("stop_barrier_margin_m", 0.08),
                                            ("stop_barrier_lag_s", 0.0),
                                            ("stop_barrier_force_fraction", 0.0),
                                            ("stop_barrier_rate_lowpass_hz", -1.0),
                                            ("stop_barrier_rate_per_s", 0.0),
                                            ("stop_barrier_passive_uncertainty", 1.0)])
def test_bad_barrier_settings_name_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"design.{key}"):
        default_config().replace(design={**ON, key: value})


@pytest.mark.parametrize("push_n", [-8000.0, -3000.0, 0.0])
@pytest.mark.parametrize("v0", [0.0, 0.3, 0.6])
def test_design_model_stays_margin_short_of_the_stop(push_n: float, v0: float) -> None:
    """The barrier's design model (body M on spring K and damper C, wheel held, the force
    reaching the body one tick late through a first-order lag of half the barrier's
    lag): a law pushing toward the compression stop with up to the force limit, from any
    state with h >= 0, never brings the rattlespace past the margin."""
    b = _barrier()
    dt = 1e-3
    a = b.decel_mps2
    # start on the barrier's boundary h = 0 (the most the design model allows)
    r = HI - b.margin_m - v0 * v0 / (2.0 * a) - b.lag_s * v0
    v, f_act, f_cmd = v0, 0.0, 0.0
    tau = 0.5 * b.lag_s
    peak = r
    for _ in range(3000):
        f_act += (f_cmd - f_act) * (1.0 - math.exp(-dt / tau))
        f_cmd = min(max(barrier_force(push_n, r, v, LO, HI, b), -8000.0), 8000.0)
        acc = (-f_act - b.stiffness_n_per_m * r - b.damping_ns_per_m * v) / b.mass_kg
        v += acc * dt
        r += v * dt
        peak = max(peak, r)
    assert peak <= HI - b.margin_m + 2e-3, f"peak {peak * 1e3:.1f} mm"


def _barrier_trace(cfg_over: Mapping[str, object], seed: int, weight_set: int, duration_s: float
                   ) -> tuple[dict[str, float], np.ndarray]:
    """A bank run on the rough course; per tick (LVDT reading, barrier's rate, force the
    barrier added)."""
    cfg = default_config().replace(design=dict(cfg_over))
    road = make_road("rough-course", 11.176, duration_s, cfg.sample_time_s, seed)
    ctrl = BankController(cached_design(cfg), cfg, "lqg", weight_set, road)
    rows: list[tuple[float, float, float]] = []
    step = ctrl.step

    def traced(reading: SensorReading, plant: RigPlant) -> float:
        u = step(reading, plant)
        rows.append((reading.rattlespace_m, float(ctrl.rt._fv[F_SB_V]),
                     ctrl.rt.stop_barrier_force))
        return u

    ctrl.step = traced  # type: ignore[method-assign]
    res = run_closed_loop(cfg, road, ctrl, seed=seed)
    return res.metrics, np.array(rows)


def test_barrier_on_the_rig_only_pushes_away_from_the_stop_it_nears() -> None:
    """Weight set 2, seed 6 of the thesis course: a force the barrier adds extends the
    suspension only while it is compressed or compressing, and vice versa."""
    m, tr = _barrier_trace(ON, 6, 2, 20.0)
    r, rate, df = tr.T
    assert np.any(df != 0.0)
    assert np.all((r[df > 0] > 0.0) | (rate[df > 0] > 0.0))
    assert np.all((r[df < 0] < 0.0) | (rate[df < 0] < 0.0))
    assert m["bump_stop_slam"] == 0.0


@pytest.mark.parametrize("seed", [1, 4, 6])
def test_weight_set_2_does_not_slam_where_passive_does_not(seed: int) -> None:
    """The issue's runs: weight set 2 rode the stops (peak 88-101 mm, slam) on these
    seeds of the thesis course; with the barrier no slam, as passive."""
    cfg = default_config().replace(design=ON)
    road = make_road("rough-course", 11.176, 30.0, cfg.sample_time_s, seed)
    passive = simulate(cfg, road, "passive", seed=seed).metrics
    assert passive["bump_stop_slam"] == 0.0
    for mode in ("lqg", "fuzzy"):
        m = simulate(cfg, road, mode, 2, seed=seed).metrics
        assert m["bump_stop_slam"] == 0.0, mode
        assert m["n_faults"] == 0.0 and m["absorbed_power"] < passive["absorbed_power"]


def test_spread_plants_do_not_slam_where_passive_does_not() -> None:
    """25 % spread, the plants of ``rig montecarlo --runs 20 --spread 0.25 --duration 20``
    (seed 1) that slammed with weight set 1 before the barrier (run 11: K = 0.59 K_nom,
    the soft-spring drift of §9.6; runs 0 and 16): with it none slams, as passive."""
    cfg = default_config().replace(design=ON)
    road = make_road("rough-course", 11.176, 20.0, cfg.sample_time_s, 1)
    params = draw_params(cfg, 20, 0.25, 1)
    for i in (0, 11, 16):
        passive = simulate(cfg, road, "passive", params=params[i], seed=1001 + i).metrics
        assert passive["bump_stop_slam"] == 0.0
        for mode in ("lqg", "fuzzy"):
            m = simulate(cfg, road, mode, 1, params=params[i], seed=1001 + i).metrics
            assert m["bump_stop_slam"] == 0.0, (i, mode)
