"""Moving bank (Ch. VI): airborne/on-ground set switching with hysteresis, the moving
subset on 2-D grids, work proportional to k, learnt thresholds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.artifact import Design
from controller.bank import BankRuntime, Blending
from controller.config import RigConfig, default_config
from controller.design import design_bank
from controller.kernels import I_DWELL, S_QS
from controller.moving_bank import (
    HIST_BINS,
    HIST_HI_LOG10,
    HIST_LO_LOG10,
    chi2_threshold_floor,
    history_add,
    history_quantile,
    neighbour_table,
    supervise,
)
from controller.reference import quarter_car_measurements
from controller.road_noise import road_velocity_intensity

V, GD = 5.0, 16e-6
DEFL_9 = [0.045, 0.04, 0.035, 0.03, 0.025, 0.02, 0.015, 0.01, 0.005]


def grid_config(deflections: list[float], scales: list[float], k: int = 3) -> RigConfig:
    return default_config().replace(
        noise={"speeds_mps": [V], "road_roughness_gd": [GD], "nominal_speed_mps": V,
               "nominal_roughness_gd": GD},
        design={"linearisation_deflections_m": deflections, "tire_damping_scales": scales},
        moving_bank={"active_models": k})


def measurements(cfg: RigConfig, n: int, seed: int, *, drop_at: int | None = None,
                 force_std: float = 300.0, deflection_m: float | None = None
                 ) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    dt = cfg.sample_time_s
    road = rng.normal(0.0, math.sqrt(road_velocity_intensity(V, GD) / dt), n)
    if drop_at is not None:
        road[drop_at:drop_at + 50] -= 2.0        # the road falls 10 cm: the wheel lifts off
    return quarter_car_measurements(cfg, dt, road, rng.normal(0.0, force_std, n), rng,
                                    deflection_m=deflection_m)


@pytest.fixture(scope="module")
def grid9() -> tuple[RigConfig, Design]:
    cfg = grid_config([0.035, 0.025, 0.015], [0.5, 1.0, 2.0])
    return cfg, design_bank(cfg)


@pytest.fixture(scope="module")
def grid27() -> tuple[RigConfig, Design]:
    cfg = grid_config(DEFL_9, [0.5, 1.0, 2.0])
    return cfg, design_bank(cfg)


def test_neighbour_table_orders_by_grid_distance() -> None:
    gi = np.array([[d, s] for d in range(3) for s in range(3)] + [[-1, -1]])
    air = np.array([False] * 9 + [True])
    nbr = neighbour_table(gi, air)
    assert nbr.shape == (10, 9)
    assert np.all(nbr[9] == -1)
    centre = 4                                           # (1, 1)
    assert nbr[centre, 0] == centre
    assert set(nbr[centre, 1:3]) == {1, 7}               # deflection neighbours first
    assert set(nbr[centre, 3:5]) == {3, 5}               # then damping neighbours
    assert set(nbr[centre, 5:]) == {0, 2, 6, 8}          # then diagonals
    for c in range(9):
        assert sorted(nbr[c]) == list(range(9))


@pytest.mark.parametrize("quantile", [0.9, 0.99, 0.999])
def test_history_quantile_matches_weighted_empirical_quantile(grid9: tuple,
                                                              quantile: float) -> None:
    """The exponentially forgotten histogram gives the exponentially weighted empirical
    quantile of what it was fed, to within one bin."""
    cfg, d = grid9
    rt = BankRuntime(d, blending=Blending.MOVING)
    fv, iv = rt._fv, rt._iv
    rng = np.random.default_rng(4)
    samples = np.concatenate([rng.exponential(2.0, 3000), rng.exponential(8.0, 3000)])
    for x in samples:                      # the second half dominates the window
        history_add(fv, iv, float(x))
    n_window = cfg.moving_bank.history_window_s / d.dt_s
    wts = (1.0 - 1.0 / n_window) ** np.arange(samples.size)[::-1]
    order = np.argsort(samples)
    cw = np.cumsum(wts[order]) / wts.sum()
    q_emp = samples[order][np.searchsorted(cw, quantile)]
    bin_factor = 10 ** ((HIST_HI_LOG10 - HIST_LO_LOG10) / HIST_BINS)
    assert history_quantile(fv, iv, quantile) == pytest.approx(q_emp, rel=bin_factor - 1.0)


def test_learnt_threshold_never_below_chi2_floor(grid9: tuple) -> None:
    cfg, d = grid9
    rt = BankRuntime(d, blending=Blending.MOVING)
    meas = measurements(cfg, 2000, seed=2)
    for k in range(2000):
        rt.step(meas["rattlespace"][k], meas["accel"][k], meas["force"][k])
    assert rt.counters()["history_samples"] > 1000
    assert rt.residual_threshold >= chi2_threshold_floor(cfg.moving_bank.threshold_quantile)


def test_lift_off_switches_to_airborne_and_back_without_chattering(grid9: tuple) -> None:
    cfg, d = grid9
    rt = BankRuntime(d, blending=Blending.MOVING)
    n, drop = 4000, 2500
    meas = measurements(cfg, n, seed=1, drop_at=drop)
    off_ground = np.flatnonzero(~meas["contact"])
    assert off_ground.size > 20                       # the plant really left the ground
    air, updates = np.zeros(n, dtype=bool), np.zeros(n, dtype=int)
    for k in range(n):
        rt.step(meas["rattlespace"][k], meas["accel"][k], meas["force"][k])
        air[k] = rt.airborne_mode
        updates[k] = rt.filter_updates
    air_ticks = np.flatnonzero(air)
    assert air_ticks.size > 0
    assert rt.counters()["set_switches"] == 2                       # one flight, no chatter
    first, last = air_ticks[0], air_ticks[-1]
    assert drop <= first <= off_ground[0] + 10          # detected by the lift-off
    assert off_ground[-1] <= last <= off_ground[-1] + 100   # back down after touch-down
    assert np.all(air[first:last + 1])                   # one contiguous airborne phase
    dwell = round(cfg.moving_bank.dwell_time_s / d.dt_s)
    assert last - first + 1 >= dwell
    k = cfg.moving_bank.active_models
    # work: k filters on the ground; airborne filter + the zero-weight sentinel in the air
    assert np.all(updates[first + 1:last + 1] == 2)
    assert np.all(updates[:first + 1] == k) and np.all(updates[last + 2:] == k)
    assert not np.any(air[:drop])                        # no false alarm before


def test_schmitt_trigger_with_dwell(grid9: tuple) -> None:
    """Drive the supervisor directly with a sentinel q oscillating between 0.7 T and
    1.3 T: one switch to airborne and none back (hysteresis 0.5); below 0.5 T it returns."""
    _, d = grid9
    rt = BankRuntime(d, blending=Blending.MOVING)
    args = (rt._st, rt._active, rt._fv, rt._iv, rt._nbr, rt._vec, rt._mat)
    T = rt.residual_threshold
    for _ in range(50):                                   # settle on the ground
        supervise(*args)
    assert not rt.airborne_mode
    for i in range(400):
        level = (1.3 if i % 2 == 0 else 0.7) * T
        rt._st[rt.active, S_QS] = level
        supervise(*args)
    assert rt.airborne_mode and rt.counters()["set_switches"] == 1
    dwell = int(rt._iv[I_DWELL])
    for _ in range(dwell + 1):
        rt._st[rt.active, S_QS] = 0.4 * T
        supervise(*args)
    assert not rt.airborne_mode and rt.counters()["set_switches"] == 2


@pytest.mark.parametrize("k", [1, 3, 5])
def test_work_is_proportional_to_k_not_the_grid(grid27: tuple, k: int) -> None:
    cfg, d = grid27
    assert d.n_models == 28
    cfg_k = cfg.replace(moving_bank={"active_models": k})
    rt = BankRuntime(d, blending=Blending.MOVING, cfg=cfg_k)
    meas = measurements(cfg, 600, seed=3)
    updates = []
    for i in range(600):
        rt.step(meas["rattlespace"][i], meas["accel"][i], meas["force"][i])
        updates.append(rt.filter_updates)
        assert int(rt.active.sum()) == k
        assert np.all(rt.firing_weight[~rt.active] == 0.0)
        assert np.all(rt.u_model[~rt.active] == 0.0)
    assert set(updates) == {k}
    full = BankRuntime(d, blending=Blending.FUZZY)
    full.step(0.0, 0.0, 0.0)
    assert full.filter_updates == 28


def test_subset_moves_towards_the_true_model_on_a_27_grid(grid27: tuple) -> None:
    """Plant linearised at 40 mm, bank started at 25 mm: the centre wanders to the
    40 mm neighbourhood; the probe slot visits every damping scale."""
    cfg, d = grid27
    rt = BankRuntime(d, blending=Blending.MOVING)
    n = 6000
    meas = measurements(cfg, n, seed=1, force_std=2000.0, deflection_m=0.04)
    start = DEFL_9[int(d.grid_index[rt.centre, 0])]
    assert start == 0.025
    centres, scales_seen = [], set()
    for i in range(n):
        rt.step(meas["rattlespace"][i], meas["accel"][i], meas["force"][i])
        centres.append(DEFL_9[int(d.grid_index[rt.centre, 0])])
        scales_seen |= {int(s) for s in d.grid_index[rt.active, 1]}
    err = np.abs(np.array(centres[n // 2:]) - 0.04)
    assert np.mean(err) < 0.5 * abs(start - 0.04)
    assert scales_seen == {0, 1, 2}
    assert rt.counters()["recentres"] >= 2
