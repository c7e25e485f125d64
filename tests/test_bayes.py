"""Bayesian MMAE blending (Eq. 4.2/4.6): log-space kernel vs direct densities, floor,
robustness, and identification of the true model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config, layer_grid
from controller.design import design_bank
from controller.road_noise import road_velocity_intensity
from controller.runtime.bank import BankRuntime, Blending
from controller.runtime.bayes import bayes_update, log_likelihood_constant
from tests.support.reference_bank import bayes_update_numpy, quarter_car_measurements

M = 2


def _kernel(p_prev: np.ndarray, q: np.ndarray, logdet: np.ndarray, floor: float,
            contrib: np.ndarray | None = None) -> np.ndarray:
    J = p_prev.size
    st_ = np.zeros((J, 3))
    st_[:, 0] = p_prev
    st_[:, 1] = q
    st_[:, 2] = 1.0 if contrib is None else contrib.astype(float)
    vec = np.array([[log_likelihood_constant(float(ld), M)] for ld in logdet])
    bayes_update(st_, 0, 1, 2, vec, 0, floor, np.arange(J, dtype=np.int64), 0, J)
    return st_[:, 0].copy()


def test_matches_eq_4_2_and_4_6_directly() -> None:
    """Without the floor acting, p_j = f_j p_j / sum f_k p_k with the Gaussian density."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        J = int(rng.integers(2, 8))
        p = rng.dirichlet(np.ones(J))
        q = rng.uniform(0.0, 6.0, J)
        logdet = rng.uniform(-20.0, -5.0, J)
        F_det = np.exp(logdet)
        dens = np.exp(-q / 2) / ((2 * math.pi) ** (M / 2) * np.sqrt(F_det))   # Eq. 4.6
        expect = dens * p / np.sum(dens * p)                                   # Eq. 4.2
        got = _kernel(p, q, logdet, floor=1e-300)
        np.testing.assert_allclose(got, expect, rtol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12).flatmap(lambda J: st.tuples(
    st.lists(st.floats(1e-3, 1.0), min_size=J, max_size=J),   # p > 0 (the floor holds)
    st.lists(st.floats(0.0, 1e12), min_size=J, max_size=J),
    st.lists(st.floats(-40.0, 5.0), min_size=J, max_size=J))))
def test_probabilities_are_a_floored_distribution(args: tuple[list[float], ...]) -> None:
    p_raw, q, logdet = (np.array(a) for a in args)
    J = p_raw.size
    p = p_raw / p_raw.sum()
    floor = 1e-4
    got = _kernel(p, q, logdet, floor)
    assert np.all(np.isfinite(got))
    assert np.all((got >= 0.0) & (got <= 1.0))
    assert got.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(got >= floor / (1.0 + J * floor) * (1 - 1e-12))     # nobody locked out
    ref = bayes_update_numpy(p, q, logdet, M, floor)
    # exp(-q/2) of two implementations differs by ~eps q/2 (relative) for large q
    rtol = 1e-9 + 1e-15 * float(np.max(q))
    np.testing.assert_allclose(got, ref, rtol=rtol, atol=1e-12)


def test_log_space_survives_underflow() -> None:
    """All densities underflow (q ~ 1e4): the direct formula is 0/0, the log form still
    favours the smallest q."""
    q = np.array([20000.0, 20010.0, 20100.0])
    assert np.all(np.exp(-q / 2) == 0.0)
    got = _kernel(np.full(3, 1 / 3), q, np.zeros(3), floor=1e-4)
    assert got[0] > 0.99 and np.argmax(got) == 0
    assert got.sum() == pytest.approx(1.0)


def test_non_contributing_models_get_zero() -> None:
    got = _kernel(np.array([0.5, 0.3, 0.2]), np.array([1.0, 2.0, 3.0]), np.zeros(3), 1e-4,
                  contrib=np.array([True, False, True]))
    assert got[1] == 0.0 and got.sum() == pytest.approx(1.0)


def test_floor_lets_a_model_come_back() -> None:
    p = np.array([1.0 - 2e-4, 1e-4, 1e-4])
    for _ in range(30):          # model 1 now explains the data much better
        p = _kernel(p, np.array([30.0, 0.5, 30.0]), np.zeros(3), 1e-4)
    assert p[1] > 0.99


def test_bayes_bank_identifies_the_true_model() -> None:
    """Data from the plant linearised at 40 mm: the 40 mm model's probability dominates
    (in a layered bank, that of the layer of the configured vehicle, which it runs)."""
    V, GD = 5.0, 16e-6
    cfg = default_config().replace(
        noise={"speeds_mps": [V], "road_roughness_gd": [GD], "nominal_speed_mps": V,
               "nominal_roughness_gd": GD},
        design={"include_airborne_model": False})
    d = design_bank(cfg)
    rng = np.random.default_rng(7)
    n = 3000
    road = rng.normal(0.0, math.sqrt(road_velocity_intensity(V, GD) / d.dt_s), n)
    meas = quarter_car_measurements(cfg, d.dt_s, road, rng.normal(0.0, 2000.0, n), rng,
                                    deflection_m=0.04)
    rt = BankRuntime(d, blending=Blending.BAYES)
    p_sum = np.zeros(d.n_models)
    for k in range(n):
        rt.step(meas["rattlespace"][k], meas["accel"][k], meas["force"][k])
        if k >= n // 2:
            p_sum += rt.probability
    dc = cfg.design
    per_layer = len(dc.linearisation_deflections_m) * len(dc.tire_damping_scales)
    j40 = (layer_grid(cfg).index((1.0, 1.0, 1.0, 1.0)) * per_layer    # layer major
           + dc.linearisation_deflections_m.index(0.04) * len(dc.tire_damping_scales)
           + dc.tire_damping_scales.index(1.0))
    assert str(d.model_names[j40]).startswith("x2_40mm")
    assert int(np.argmax(p_sum)) == j40
    assert p_sum[j40] / (n - n // 2) > 0.6
