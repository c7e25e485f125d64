"""LQ design: human filter, augmented plant, Van Loan cost discretisation, DARE gains."""

from __future__ import annotations

import control
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from controller.human_filter import discretize_zoh, human_filter
from controller.lq import augmented_plant, discretize_cost, dlqr_cross, lq_gain, lq_problem
from controller.plant import model_family

CFG = default_config()
DT = CFG.sample_time_s
HF = human_filter(CFG.design, DT)
GROUND = [m for m in model_family(CFG) if not m.airborne]
AIRBORNE = next(m for m in model_family(CFG) if m.airborne)
SETS = CFG.design.weight_sets


def test_human_filter_matches_transfer_function() -> None:
    num, den = CFG.design.human_filter_num, CFG.design.human_filter_den
    for w in (0.3, 5.0, 30.02, 200.0):
        s = 1j * w
        ref = np.polyval(num, s) / np.polyval(den, s)
        got = HF.Cf @ np.linalg.solve(s * np.eye(2) - HF.Af, HF.Bf)
        assert got == pytest.approx(ref, rel=1e-12)


def test_human_filter_zoh_matches_python_control() -> None:
    sysd = control.c2d(control.ss(HF.Af, HF.Bf.reshape(2, 1), HF.Cf.reshape(1, 2), 0.0), DT,
                       method="zoh")
    np.testing.assert_allclose(HF.Ad, sysd.A, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(HF.Bd, np.asarray(sysd.B).ravel(), rtol=1e-10, atol=1e-18)


def test_augmented_filter_output_is_filtered_acceleration() -> None:
    """u -> y_f of the augmented plant equals F(s) * (u -> zs'') incl. the u/M feedthrough."""
    model = GROUND[1]
    aug = augmented_plant(model, HF, SETS[0])
    c_yf = np.concatenate([np.zeros(4), HF.Cf])
    num, den = CFG.design.human_filter_num, CFG.design.human_filter_den
    for w in (1.0, 8.0, 60.0):
        s = 1j * w
        g_yf = c_yf @ np.linalg.solve(s * np.eye(6) - aug.A, aug.B)
        g_acc = model.A[2] @ np.linalg.solve(s * np.eye(4) - model.A, model.B2) \
            + 1.0 / CFG.vehicle.sprung_mass_kg
        f = np.polyval(num, s) / np.polyval(den, s)
        assert g_yf == pytest.approx(f * g_acc, rel=1e-10)


def _brute_force_stage_cost(A: np.ndarray, B: np.ndarray, Qc: np.ndarray, Rc: float,
                            z0: np.ndarray, u: float, dt: float) -> float:
    def integrand(t: float) -> float:
        Phi, Gam = discretize_zoh(A, B, t)
        z = Phi @ z0 + Gam * u
        return float(z @ Qc @ z + Rc * u * u)

    val, _ = scipy.integrate.quad(integrand, 0.0, dt, epsabs=0.0, epsrel=1e-12, limit=200)
    return val


@pytest.mark.parametrize("dt", [DT, 0.02])
def test_discretised_cost_equals_quadrature_of_continuous_cost(dt: float) -> None:
    rng = np.random.default_rng(1)
    aug = augmented_plant(GROUND[0], HF, SETS[0])
    prob = discretize_cost(aug.A, aug.B, aug.Qc, aug.Rc, dt)
    for _ in range(3):
        z0 = rng.normal(size=6) * np.array([0.01, 0.005, 0.2, 0.5, 0.01, 0.1])
        u = float(rng.normal() * 500.0)
        ref = _brute_force_stage_cost(aug.A, aug.B, aug.Qc, aug.Rc, z0, u, dt)
        got = z0 @ prob.Qd @ z0 + 2.0 * u * (z0 @ prob.Nd) + prob.Rd * u * u
        assert got == pytest.approx(ref, rel=1e-8)
    # the cross term is real (not an artefact): it is not negligible against Qd, Rd
    assert np.linalg.norm(prob.Nd) > 0.0


@pytest.mark.parametrize("w", range(len(SETS)))
@pytest.mark.parametrize("j", range(len(GROUND)))
def test_lq_gain_matches_python_control_dlqr(j: int, w: int) -> None:
    prob = lq_problem(GROUND[j], HF, SETS[w])
    K = lq_gain(GROUND[j], HF, SETS[w])
    Kc, _, _ = control.dlqr(prob.Ad, prob.Bd.reshape(6, 1), prob.Qd, np.array([[prob.Rd]]),
                            prob.Nd.reshape(6, 1))
    np.testing.assert_allclose(K, np.asarray(Kc).ravel(), rtol=1e-6)


def test_lq_gain_matches_riccati_iteration() -> None:
    prob = lq_problem(GROUND[2], HF, SETS[1])
    A, B, N, R = prob.Ad, prob.Bd.reshape(6, 1), prob.Nd.reshape(6, 1), prob.Rd
    P = prob.Qd.copy()
    Kk = np.zeros((1, 6))
    for _ in range(100_000):
        Kk = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A + N.T)
        P_next = A.T @ P @ A - (A.T @ P @ B + N) @ Kk + prob.Qd
        if np.max(np.abs(P_next - P)) <= 1e-15 * np.max(np.abs(P_next)):
            break
        P = P_next
    else:
        pytest.fail("Riccati iteration did not converge")
    np.testing.assert_allclose(lq_gain(GROUND[2], HF, SETS[1]), Kk.ravel(), rtol=1e-6)


@pytest.mark.parametrize("delay_ticks", [2, 3])
def test_actuated_gain_with_longer_delays_is_the_riccati_fixed_point(delay_ticks: int
                                                                     ) -> None:
    """With the flow feedforward and D >= 2 pending commands the DARE pencil needs the
    state balancing (and here scipy's second attempt) of ``dlqr_cross``; the gain is the
    fixed point of the plain Riccati recursion all the same."""
    from controller.actuator import servo_model
    from controller.lq import actuated_lq_gain, actuated_lq_problem

    cfg = CFG.replace(design={"compute_delay_ticks": delay_ticks})
    servo = servo_model(cfg)
    model = GROUND[0]
    prob = actuated_lq_problem(model, HF, SETS[1], servo)
    n = prob.Ad.shape[0]
    A, B, N, R = prob.Ad, prob.Bd.reshape(n, 1), prob.Nd.reshape(n, 1), prob.Rd
    P = prob.Qd.copy()
    Kk = np.zeros((1, n))
    for _ in range(20_000):
        Kk = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A + N.T)
        P = A.T @ P @ A - (A.T @ P @ B + N) @ Kk + prob.Qd
        P = 0.5 * (P + P.T)
    np.testing.assert_allclose(actuated_lq_gain(model, HF, SETS[1], servo), Kk.ravel(),
                               rtol=1e-7)


@pytest.mark.parametrize("w", range(len(SETS)))
def test_lq_closed_loop_stable_for_every_model(w: int) -> None:
    for model in GROUND:
        prob = lq_problem(model, HF, SETS[w])
        K = lq_gain(model, HF, SETS[w])
        rho = np.max(np.abs(np.linalg.eigvals(prob.Ad - np.outer(prob.Bd, K))))
        assert rho < 1.0


def test_airborne_gain_is_zero_and_its_dare_is_ill_posed() -> None:
    for w in SETS:
        assert np.all(lq_gain(AIRBORNE, HF, w) == 0.0)
    prob = lq_problem(AIRBORNE, HF, SETS[0])
    # centre-of-mass modes are uncontrollable by an internal force: eigenvalue 1 stays
    ctrb = control.ctrb(prob.Ad, prob.Bd.reshape(6, 1))
    assert np.linalg.matrix_rank(ctrb, tol=1e-9 * np.linalg.norm(ctrb)) < 6
    with pytest.raises(ValueError):
        dlqr_cross(prob.Ad, prob.Bd, prob.Qd, prob.Rd, prob.Nd)


def test_bad_weights_rejected() -> None:
    with pytest.raises(ValueError, match="rho3"):
        augmented_plant(GROUND[0], HF, (1.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError):
        augmented_plant(GROUND[0], HF, (-1.0, 1.0, 1e-8, 1.0))


@settings(max_examples=15, deadline=None)
@given(rho1=st.floats(1e-3, 1e3), rho2=st.floats(1e-3, 1e3), rho3=st.floats(1e-10, 1e-6))
def test_lq_gain_is_stabilising_for_any_reasonable_weights(rho1: float, rho2: float,
                                                           rho3: float) -> None:
    model = GROUND[1]
    prob = lq_problem(model, HF, (rho1, rho2, rho3, 1.0))
    K = lq_gain(model, HF, (rho1, rho2, rho3, 1.0))
    assert np.max(np.abs(np.linalg.eigvals(prob.Ad - np.outer(prob.Bd, K)))) < 1.0
    # optimal cost-to-go is positive semidefinite
    _, P = dlqr_cross(prob.Ad, prob.Bd, prob.Qd, prob.Rd, prob.Nd)
    assert np.min(np.linalg.eigvalsh(0.5 * (P + P.T))) > -1e-9 * np.max(np.abs(P))
