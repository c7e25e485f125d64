"""The batched filter-DARE solver (controller/dare.py) against scipy's QZ solver and
python-control, on every system the default design solves and on random systems; its
results do not depend on the stack a system shares; it falls back to QZ where doubling
cannot converge."""

from __future__ import annotations

import control
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

import controller.dare as dare
from controller.config import default_config
from controller.design import design_models, measurement_noise_cov
from controller.kalman import bias_augmented, steady_state_kalman, steady_state_kalman_stack
from controller.road_noise import noise_table_entries

CFG = default_config()
R = measurement_noise_cov(CFG)


def _bank_systems() -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Every (model, noise entry) filter system of the default design, bias states on."""
    dt = CFG.sample_time_s
    bias_qd = np.array([CFG.design.filter_rattlespace_bias_drift ** 2,
                        CFG.design.filter_accel_bias_drift ** 2]) * dt
    out, names = [], []
    for md in design_models(CFG):
        for _v, _gd, w in noise_table_entries(CFG.noise):
            out.append(bias_augmented(md.dfm.Phi, md.fm.C,
                                      md.dfm.Qd_unit * w + md.dfm.Qd_fixed, bias_qd)[:3])
            names.append(md.model.name)
    return (np.stack([o[0] for o in out]), np.stack([o[1] for o in out]),
            np.stack([o[2] for o in out]), names)


PHI, C, Q, NAMES = _bank_systems()


def _residual(P: np.ndarray, Phi: np.ndarray, Cm: np.ndarray, Qm: np.ndarray) -> float:
    F = Cm @ P @ Cm.T + R
    K = Phi @ P @ Cm.T
    res = Phi @ P @ Phi.T - K @ np.linalg.solve(F, K.T) + Qm - P
    return float(np.max(np.abs(res)) / np.max(np.abs(P)))


def test_every_default_system_agrees_with_scipy_qz() -> None:
    P = dare.solve_filter_dares(PHI, C, Q, R)
    assert P.shape == PHI.shape
    S = len(noise_table_entries(CFG.noise))
    # every model, each at one noise entry, the entry turning over from model to model
    for i in (j * S + j % S for j in range(len(NAMES) // S)):
        ref = scipy.linalg.solve_discrete_are(PHI[i].T, C[i].T, Q[i], R)
        scale = np.max(np.abs(ref))
        np.testing.assert_allclose(P[i], ref, rtol=0.0, atol=1e-8 * scale,
                                   err_msg=f"system {i} ({NAMES[i]})")
        assert _residual(P[i], PHI[i], C[i], Q[i]) < 1e-10
        np.testing.assert_array_equal(P[i], P[i].T)


def test_doubling_solves_the_default_bank_without_the_fallback(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The speed claim: no system of the default design needs the QZ solver."""
    def refuse(*_a: object, **_k: object) -> None:
        raise AssertionError("QZ fallback used")
    monkeypatch.setattr(dare.scipy.linalg, "solve_discrete_are", refuse)
    P = dare.solve_filter_dares(PHI, C, Q, R)
    assert np.all(np.isfinite(P))


def test_a_system_gets_the_same_bits_alone_and_in_any_stack() -> None:
    P_all = dare.solve_filter_dares(PHI, C, Q, R)
    rng = np.random.default_rng(3)
    for i in rng.choice(len(NAMES), size=12, replace=False):
        alone = dare.solve_filter_dares(PHI[i:i + 1], C[i:i + 1], Q[i:i + 1], R)
        np.testing.assert_array_equal(alone[0], P_all[i])
        kf = steady_state_kalman(PHI[i], C[i], Q[i], R)
        np.testing.assert_array_equal(kf.P_prior, P_all[i])


def test_kalman_stack_matches_single_system_gains() -> None:
    md = design_models(CFG)[5]
    ws = np.array([w for _v, _g, w in noise_table_entries(CFG.noise)])
    Qs = md.dfm.Qd_unit * ws[:, None, None]
    n = len(ws)
    t = steady_state_kalman_stack(np.broadcast_to(md.dfm.Phi, (n, 4, 4)),
                                  np.broadcast_to(md.fm.C, (n, 2, 4)), Qs, R)
    for s in range(n):
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, Qs[s], R)
        np.testing.assert_array_equal(t.L[s], kf.L)
        np.testing.assert_array_equal(t.F_inv[s], kf.F_inv)
        assert t.logdet[s] == kf.logdet


def test_no_stabilising_solution_names_the_system() -> None:
    """A marginal unobservable mode (an integrator C does not see): doubling cannot
    converge, the QZ fallback returns a non-stabilising solution and the stack says
    which system failed."""
    Phi = np.array([[1.0, 0.0], [0.0, 0.5]])
    Cm = np.array([[0.0, 1.0], [0.0, 1.0]])
    good = np.array([[0.9, 0.1], [0.0, 0.5]])
    Cg = np.array([[1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match="system 1"):
        steady_state_kalman_stack(np.stack([good, Phi]), np.stack([Cg, Cm]),
                                  np.stack([np.eye(2), np.eye(2)]), np.eye(2))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), unstable=st.booleans())
def test_random_systems_agree_with_python_control(seed: int, n: int, unstable: bool) -> None:
    """Random detectable systems (full-rank noise, two measurements), some with an
    unstable Phi: P agrees with python-control's dlqe."""
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(n, n))
    radius = 1.3 if unstable else 0.95
    Phi *= radius / max(np.max(np.abs(np.linalg.eigvals(Phi))), 1e-6)
    Cm = rng.normal(size=(2, n))
    Bq = rng.normal(size=(n, n))
    Qm = Bq @ Bq.T + 1e-3 * np.eye(n)
    Rm = np.diag(rng.uniform(0.1, 2.0, size=2))
    P = dare.solve_filter_dares(Phi[None], Cm[None], Qm[None], Rm)[0]
    _L, P_ref, _E = control.dlqe(Phi, np.eye(n), Cm, Qm, Rm)
    scale = np.max(np.abs(P_ref))
    np.testing.assert_allclose(P, P_ref, rtol=0.0, atol=1e-7 * scale)
