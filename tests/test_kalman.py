"""Kalman filters: Van Loan noise, DARE vs independent solvers, fused update vs textbook
Eq. 3.3-3.8, airborne regularisation, road-noise intensity."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config, layer_params
from controller.design import design_models, measurement_noise_cov
from controller.kalman import (
    discretize_filter_model,
    filter_model,
    fused_prior_update,
    process_noise_cov,
    steady_state_kalman,
)
from controller.plant import model_family
from controller.road_noise import (
    ISO_CLASS_GD,
    iso_class_gd,
    nearest_noise_entry,
    noise_table_entries,
    road_velocity_intensity,
)

CFG = default_config()
DT = CFG.sample_time_s
R = measurement_noise_cov(CFG)
MDS = design_models(CFG)
W_NOM = road_velocity_intensity(CFG.noise.nominal_speed_mps, CFG.noise.nominal_roughness_gd)
#: the models the per-model checks below run on: every fifth of the bank (the stride is
#: prime to the three tire models of a layer, so every linearisation point and every
#: layer axis comes up) and the airborne model.  Every model's DARE is checked against
#: scipy's QZ solver in tests/test_dare.py.
SAMPLE = sorted(set(range(0, len(MDS), 5))
                | {j for j, md in enumerate(MDS) if md.model.airborne})


def _sda_filter_dare(Phi: np.ndarray, C: np.ndarray, Q: np.ndarray,
                     Rm: np.ndarray) -> np.ndarray:
    """Structure-preserving doubling for P = Phi P Phi' - Phi P C'(CPC'+R)^-1 C P Phi' + Q."""
    A = Phi.T.copy()
    G = C.T @ np.linalg.solve(Rm, C)
    H = Q.copy()
    n = A.shape[0]
    for _ in range(200):
        Minv = np.linalg.inv(np.eye(n) + G @ H)
        A_next = A @ Minv @ A
        G_next = G + A @ Minv @ G @ A.T
        H_next = H + A.T @ H @ Minv @ A
        if np.max(np.abs(H_next - H)) <= 1e-14 * np.max(np.abs(H_next)):
            return 0.5 * (H_next + H_next.T)
        A, G, H = A_next, G_next, H_next
    raise AssertionError("doubling did not converge")


def test_process_noise_matches_quadrature() -> None:
    md = MDS[1]
    dt = 0.01

    def integrand(s: float) -> np.ndarray:
        E = scipy.linalg.expm(md.fm.A * s)
        return (E @ np.outer(md.fm.B1, md.fm.B1) @ E.T * W_NOM).ravel()

    ref, _ = scipy.integrate.quad_vec(integrand, 0.0, dt, epsabs=0.0, epsrel=1e-12)
    got = process_noise_cov(md.fm.A, md.fm.B1, W_NOM, dt)
    np.testing.assert_allclose(got.ravel(), ref, rtol=1e-9, atol=1e-12 * np.max(np.abs(ref)))


def test_zoh_discretisation_matches_python_control() -> None:
    md = MDS[0]
    sysd = control.c2d(control.ss(md.fm.A, np.column_stack([md.fm.B2, md.fm.G]),
                                  np.eye(4), 0.0), DT, method="zoh")
    np.testing.assert_allclose(md.dfm.Phi, sysd.A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(md.dfm.Gamma_u, np.asarray(sysd.B)[:, 0], rtol=1e-9, atol=1e-16)
    np.testing.assert_allclose(md.dfm.Gamma_g, np.asarray(sysd.B)[:, 1], rtol=1e-9, atol=1e-16)


@pytest.mark.parametrize("j", SAMPLE)
def test_kalman_matches_python_control_dlqe_and_doubling(j: int) -> None:
    md = MDS[j]
    for _v, _gd, w_int in noise_table_entries(CFG.noise)[::6]:
        Qd = md.dfm.Qd_unit * w_int
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, Qd, R)
        if md.model.airborne:
            # relative states: stable and noise-free; centre of mass: unobservable.
            # The exact gain is 0 -- both solvers agree to round-off.
            P2 = _sda_filter_dare(md.dfm.Phi, md.fm.C, Qd, R)
            assert np.max(np.abs(kf.L)) < 1e-6
            assert np.max(np.abs(P2 @ md.fm.C.T)) < 1e-6 * np.max(np.abs(R))
            np.testing.assert_allclose(kf.F, R, rtol=1e-6, atol=1e-6 * R[0, 0])
            continue
        # python-control: predictor gain Phi L and the prior covariance
        Lp, P, _ = control.dlqe(md.dfm.Phi, np.eye(4), md.fm.C, Qd, R)
        np.testing.assert_allclose(kf.P_prior, P, rtol=1e-6, atol=1e-6 * np.max(np.abs(P)))
        np.testing.assert_allclose(md.dfm.Phi @ kf.L, Lp, rtol=1e-6,
                                   atol=1e-6 * np.max(np.abs(Lp)))
        P2 = _sda_filter_dare(md.dfm.Phi, md.fm.C, Qd, R)
        L2 = P2 @ md.fm.C.T @ np.linalg.inv(md.fm.C @ P2 @ md.fm.C.T + R)
        np.testing.assert_allclose(kf.L, L2, rtol=1e-6, atol=1e-6 * np.max(np.abs(L2)))


def test_steady_state_covariance_is_fixed_point_of_eq_3_3_to_3_8() -> None:
    md = MDS[1]
    Qd = md.dfm.Qd_unit * W_NOM
    kf = steady_state_kalman(md.dfm.Phi, md.fm.C, Qd, R)
    C = md.fm.C
    F = C @ kf.P_prior @ C.T + R                          # 3.3
    L = kf.P_prior @ C.T @ np.linalg.inv(F)               # 3.4
    P_post = kf.P_prior - L @ C @ kf.P_prior              # 3.6
    P_next = md.dfm.Phi @ P_post @ md.dfm.Phi.T + Qd      # 3.8
    np.testing.assert_allclose(P_next, kf.P_prior, rtol=1e-8,
                               atol=1e-10 * np.max(np.abs(kf.P_prior)))
    np.testing.assert_allclose(kf.F, F, rtol=1e-12)
    np.testing.assert_allclose(kf.F @ kf.F_inv, np.eye(2), atol=1e-10)
    assert kf.logdet == pytest.approx(math.log(np.linalg.det(F)), rel=1e-12)


@pytest.mark.parametrize("j", SAMPLE)
def test_fused_update_equals_textbook_filter_on_random_data(j: int) -> None:
    md = MDS[j]
    g = CFG.vehicle.gravity_mps2
    kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W_NOM, R)
    fu = fused_prior_update(md.dfm.Phi, md.dfm.Gamma_u, md.dfm.Gamma_g, g, md.fm.C,
                            md.fm.D, md.fm.y_offset, kf.L)
    rng = np.random.default_rng(j)
    x_text = rng.normal(size=4) * 0.01
    x_fused = x_text.copy()
    for _ in range(200):
        y = rng.normal(size=2) * np.array([0.01, 2.0]) + np.array([0.018, 0.0])
        u = float(rng.normal() * 1000.0)
        # Eq. 3.9, 3.5, 3.7 with the steady-state gain
        r = y - md.fm.C @ x_text - md.fm.D * u - md.fm.y_offset
        x_post = x_text + kf.L @ r
        x_text = md.dfm.Phi @ x_post + md.dfm.Gamma_u * u + md.dfm.Gamma_g * g
        x_fused = fu.A @ x_fused + fu.By @ y + fu.Bu * u + fu.b
        scale = max(1.0, float(np.max(np.abs(x_text))))
        np.testing.assert_allclose(x_fused, x_text, rtol=0.0, atol=1e-10 * scale)


def test_static_equilibrium_is_fixed_point_of_every_ground_filter() -> None:
    """Gravity handling: at rest y = [M g / K, 0], u = 0 and x = xbar_j stays put, for the
    on-ground filters of every layer of the bank (M, K: the layer's)."""
    g = CFG.vehicle.gravity_mps2
    ground = [md for md in MDS if not md.model.airborne]
    layers = layer_params(CFG)
    per_layer = len(ground) // len(layers)          # layer major (design_models)
    assert per_layer * len(layers) == len(ground)
    for j, md in enumerate(ground):
        mass, spring, _ = layers[j // per_layer]
        y_rest = np.array([mass * g / spring, 0.0])
        xbar = md.model.equilibrium
        assert xbar is not None
        np.testing.assert_allclose(md.dfm.Phi @ xbar + md.dfm.Gamma_g * g, xbar, atol=1e-12)
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W_NOM, R)
        fu = fused_prior_update(md.dfm.Phi, md.dfm.Gamma_u, md.dfm.Gamma_g, g, md.fm.C,
                                md.fm.D, md.fm.y_offset, kf.L)
        np.testing.assert_allclose(fu.A @ xbar + fu.By @ y_rest + fu.b, xbar, atol=1e-12)


def test_airborne_plain_dare_fails_and_regularised_filter_is_stable() -> None:
    air_true = next(m for m in model_family(CFG) if m.airborne)
    Phi_true = scipy.linalg.expm(air_true.A * DT)
    Q = process_noise_cov(air_true.A, air_true.B1, W_NOM, DT)
    with pytest.raises(ValueError):
        steady_state_kalman(Phi_true, air_true.C_meas, Q, R)
    md = next(m for m in MDS if m.model.airborne)
    for _v, _gd, w_int in noise_table_entries(CFG.noise):
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * w_int, R)
        A = md.dfm.Phi @ (np.eye(4) - kf.L @ md.fm.C)
        assert np.max(np.abs(np.linalg.eigvals(A))) < 1.0


def test_airborne_regularisation_leaves_input_output_behaviour_unchanged() -> None:
    """Only the unobservable centre-of-mass modes change: identical Markov parameters
    C A^k [B2, G-free] from u to the measurements, so identical residuals."""
    air_true = next(m for m in model_family(CFG) if m.airborne)
    fm = filter_model(air_true, CFG)
    C = air_true.C_meas
    Ak_true = np.eye(4)
    Ak_reg = np.eye(4)
    for _ in range(8):
        np.testing.assert_allclose(C @ Ak_reg @ fm.B2, C @ Ak_true @ air_true.B2,
                                   rtol=1e-12, atol=1e-12 * np.linalg.norm(C @ Ak_true @ fm.B2))
        np.testing.assert_allclose(C @ Ak_reg, C @ Ak_true, rtol=1e-12,
                                   atol=1e-9 * max(1.0, np.linalg.norm(C @ Ak_true)))
        Ak_true = Ak_true @ air_true.A
        Ak_reg = Ak_reg @ fm.A
    # gravity acts on relative motion in neither model
    G_true = np.array([0.0, 0.0, -1.0, -1.0])
    np.testing.assert_allclose(C @ G_true, [0.0, 0.0])


def test_velocity_leak_fixes_bias_sensitivity() -> None:
    """Documented reason for design.filter_velocity_leak_hz: without it, a rattlespace
    bias drives the velocity estimate ~1e4 times further."""
    def dc_velocity_per_rattle_bias(cfg_leak: float) -> float:
        cfg = CFG.replace(design={"filter_velocity_leak_hz": cfg_leak})
        md = design_models(cfg)[1]
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W_NOM, R)
        A = md.dfm.Phi @ (np.eye(4) - kf.L @ md.fm.C)
        dc = np.linalg.solve(np.eye(4) - A, md.dfm.Phi @ kf.L)
        return float(abs(dc[2, 0]))

    assert dc_velocity_per_rattle_bias(0.0) > 100.0 * dc_velocity_per_rattle_bias(0.1)


def test_iso_classes_and_intensity() -> None:
    assert ISO_CLASS_GD["A"] == pytest.approx(16e-6)
    assert iso_class_gd("h") == pytest.approx(262144e-6)
    assert iso_class_gd("D") == pytest.approx(1024e-6)
    with pytest.raises(ValueError):
        iso_class_gd("Z")
    with pytest.raises(ValueError):
        road_velocity_intensity(-1.0, 1e-3)
    with pytest.raises(ValueError):
        road_velocity_intensity(10.0, float("nan"))
    # closed form: one-sided velocity PSD (2 pi f)^2 Gd(f/V)/V = 2 W at any f
    V, gd = 11.176, 1024e-6
    for f in (0.5, 3.0, 20.0):
        n = f / V
        one_sided = (2 * math.pi * f) ** 2 * gd * (n / 0.1) ** -2 / V
        assert one_sided == pytest.approx(2.0 * road_velocity_intensity(V, gd), rel=1e-12)


def test_intensity_against_synthesised_iso_road() -> None:
    """Independent check: synthesise an ISO road (random-phase sinusoids), sample its
    velocity at 1 kHz, Welch PSD level in 1-10 Hz equals the one-sided 2 W."""
    rng = np.random.default_rng(7)
    V, gd = 11.176, 256e-6
    n = np.linspace(0.011, 2.83, 1500)
    dn = n[1] - n[0]
    amp = np.sqrt(2.0 * gd * (n / 0.1) ** -2 * dn)
    phase = rng.uniform(0, 2 * np.pi, n.size)
    t = np.arange(0, 40.0, 1e-3)
    # velocity of sum_i a_i cos(2 pi n_i V t + phi_i)
    w_dot = np.zeros_like(t)
    for a, ni, ph in zip(amp, n, phase, strict=True):
        w_dot -= a * 2 * np.pi * ni * V * np.sin(2 * np.pi * ni * V * t + ph)
    f, pxx = scipy.signal.welch(w_dot, fs=1000.0, nperseg=8192)
    band = (f > 1.0) & (f < 10.0)
    level = float(np.mean(pxx[band]))
    assert level == pytest.approx(2.0 * road_velocity_intensity(V, gd), rel=0.1)


@settings(max_examples=50, deadline=None)
@given(speed=st.floats(0.0, 60.0), gd=st.floats(1e-7, 1.0))
def test_nearest_noise_entry_is_valid_index(speed: float, gd: float) -> None:
    speeds = np.array(CFG.noise.speeds_mps)
    gds = np.array(CFG.noise.road_roughness_gd)
    s = nearest_noise_entry(speeds, gds, speed, gd)
    assert 0 <= s < speeds.size * gds.size
    i_s, i_r = divmod(s, gds.size)
    assert abs(speeds[i_s] - speed) == pytest.approx(np.min(np.abs(speeds - speed)))
    assert abs(math.log(gds[i_r] / gd)) == pytest.approx(np.min(np.abs(np.log(gds / gd))))


def test_discretize_filter_model_noise_scales_linearly() -> None:
    md = MDS[0]
    d2 = discretize_filter_model(md.fm, DT)
    np.testing.assert_allclose(d2.Qd_unit * 3.0, process_noise_cov(md.fm.A, md.fm.B1, 3.0, DT),
                               rtol=1e-12)
