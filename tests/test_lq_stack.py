"""The stacked LQ solver (controller.lq.dlqr_cross_stack) against scipy's QZ solver and
python-control on every problem the default design solves and on random problems with a
cross term; a problem's result does not depend on the stack it shares; a failing problem
is named, by stack index and, in the design, by model and weight set."""

from __future__ import annotations

import re

import control
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

import controller.dare as dare
from controller.actuator import servo_model
from controller.config import default_config
from controller.design import design_bank, design_models
from controller.human_filter import human_filter
from controller.lq import (
    DiscreteLQProblem,
    LQStackError,
    actuated_lq_problem,
    dlqr_cross,
    dlqr_cross_stack,
    lq_problem,
)

CFG = default_config()
HF = human_filter(CFG.design, CFG.sample_time_s)
SERVO = servo_model(CFG)
GROUND = [md.model for md in design_models(CFG) if not md.model.airborne]
AIRBORNE = next(md.model for md in design_models(CFG) if md.model.airborne)


def _stack(probs: list[DiscreteLQProblem]) -> tuple[np.ndarray, ...]:
    return (np.stack([p.Ad for p in probs]), np.stack([p.Bd for p in probs]),
            np.stack([p.Qd for p in probs]), np.array([p.Rd for p in probs]),
            np.stack([p.Nd for p in probs]))


def _qz_gain(p: DiscreteLQProblem) -> np.ndarray:
    """The gain by scipy's QZ solver on the same balanced, unit-input problem (the
    method dlqr_cross used alone before the stack)."""
    n = p.Ad.shape[0]
    _, (t, _) = scipy.linalg.matrix_balance(p.Ad, permute=False, separate=True)
    scale = 1.0 / np.sqrt(p.Rd)
    Ab = p.Ad / t[:, None] * t[None, :]
    Qb = p.Qd * t[:, None] * t[None, :]
    Bv = (p.Bd / t).reshape(n, 1) * scale
    Nv = (p.Nd * t).reshape(n, 1) * scale
    Pb = scipy.linalg.solve_discrete_are(Ab, Bv, Qb, np.eye(1), s=Nv)
    Kv = np.linalg.solve(np.eye(1) + Bv.T @ Pb @ Bv, Bv.T @ Pb @ Ab + Nv.T)
    out: np.ndarray = (Kv * scale).reshape(n) / t
    return out


#: every fourth on-ground model of the default (every layer-axis value and operating
#: point), both weight sets, the actuated problems the design solves
SAMPLE = [actuated_lq_problem(m, HF, w, SERVO) for m in GROUND[::4]
          for w in CFG.design.weight_sets]


def test_default_problems_agree_with_scipy_qz() -> None:
    K, P = dlqr_cross_stack(*_stack(SAMPLE))
    for i, p in enumerate(SAMPLE):
        ref = _qz_gain(p)
        np.testing.assert_allclose(K[i], ref, rtol=0.0, atol=1e-9 * np.max(np.abs(ref)),
                                   err_msg=f"problem {i}")
        # P is the Riccati solution with the cross term
        n = p.Ad.shape[0]
        B, N = p.Bd.reshape(n, 1), p.Nd.reshape(n, 1)
        gain = np.linalg.solve(p.Rd + B.T @ P[i] @ B, B.T @ P[i] @ p.Ad + N.T)
        res = p.Ad.T @ P[i] @ p.Ad - (p.Ad.T @ P[i] @ B + N) @ gain + p.Qd - P[i]
        assert np.max(np.abs(res)) < 1e-9 * np.max(np.abs(P[i]))


def test_doubling_solves_the_default_problems_without_the_fallback(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Neither QZ path runs for the default's problems: the doubling solves them all."""
    def refuse(*_a: object, **_k: object) -> None:
        raise AssertionError("QZ fallback used")
    monkeypatch.setattr(scipy.linalg, "solve_discrete_are", refuse)
    K, _ = dlqr_cross_stack(*_stack(SAMPLE))
    assert np.all(np.isfinite(K))


def test_a_problem_gets_the_same_bits_alone_and_in_any_stack() -> None:
    K, _ = dlqr_cross_stack(*_stack(SAMPLE))
    rng = np.random.default_rng(3)
    for i in rng.choice(len(SAMPLE), size=6, replace=False):
        p = SAMPLE[i]
        alone, _ = dlqr_cross(p.Ad, p.Bd, p.Qd, p.Rd, p.Nd)
        assert np.array_equal(alone, K[i])
        others = [SAMPLE[j] for j in rng.choice(len(SAMPLE), size=5)]
        Ks, _ = dlqr_cross_stack(*_stack([*others[:2], p, *others[2:]]))
        assert np.array_equal(Ks[2], K[i])


def test_ideal_actuator_problems_agree_with_python_control() -> None:
    probs = [lq_problem(m, HF, w) for m in GROUND[::40] for w in CFG.design.weight_sets]
    K, _ = dlqr_cross_stack(*_stack(probs))
    for i, p in enumerate(probs):
        ref, _, _ = control.dlqr(p.Ad, p.Bd.reshape(-1, 1), p.Qd, p.Rd,
                                 p.Nd.reshape(-1, 1))
        np.testing.assert_allclose(K[i], ref.ravel(), rtol=1e-6)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 7), unstable=st.booleans())
def test_random_problems_with_cross_term_agree_with_python_control(
        seed: int, n: int, unstable: bool) -> None:
    rng = np.random.default_rng(seed)
    S = 3
    A = rng.standard_normal((S, n, n))
    A /= np.max(np.abs(np.linalg.eigvals(A)), axis=1)[:, None, None]
    A *= 1.2 if unstable else 0.9
    B = rng.standard_normal((S, n))
    G = rng.standard_normal((S, n + 1, n + 1))
    W = G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(n + 1)   # [[Q, N], [N', R]] > 0
    Q, N, R = W[:, :n, :n], W[:, :n, n], W[:, n, n]
    K, _ = dlqr_cross_stack(A, B, Q, R, N)
    for i in range(S):
        ref, _, _ = control.dlqr(A[i], B[i].reshape(n, 1), Q[i], R[i], N[i].reshape(n, 1))
        np.testing.assert_allclose(K[i], ref.ravel(), rtol=1e-6, atol=1e-9)


def test_no_stabilising_solution_names_the_problem() -> None:
    """The airborne model's centre of mass cannot be moved by an internal force: its
    DARE has no stabilising solution, and the stack says which problem it was."""
    bad = lq_problem(AIRBORNE, HF, CFG.design.weight_sets[0])
    good = lq_problem(GROUND[0], HF, CFG.design.weight_sets[0])
    with pytest.raises(LQStackError, match=r"^system 1: ") as info:
        dlqr_cross_stack(*_stack([good, bad, good]))
    assert info.value.index == 1
    with pytest.raises(ValueError) as alone:
        dlqr_cross(bad.Ad, bad.Bd, bad.Qd, bad.Rd, bad.Nd)
    assert not str(alone.value).startswith("system ")


def test_design_names_the_model_and_weight_set_it_cannot_solve(
        monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = CFG.replace(design={"sprung_mass_scales": [1.0], "spring_rate_scales": [1.0],
                              "damping_scales": [1.0], "tire_stiffness_scales": [1.0]})
    real = dare.doubling_dares

    def fail_third(*args: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        P, ok = real(*args)
        if args[0].shape[1] > 5:        # the LQ stack (the filters' systems are 5 x 5)
            P[2] = np.nan
            ok[2] = False
        return P, ok

    def refuse(*_a: object, **_k: object) -> None:
        raise ValueError("refused")
    monkeypatch.setattr("controller.lq.doubling_dares", fail_third)
    monkeypatch.setattr(scipy.linalg, "solve_discrete_are", refuse)
    # the stack is model major, weight sets minor: problem 2 is model 1, weight set 1
    name = [md.model.name for md in design_models(cfg) if not md.model.airborne][1]
    with pytest.raises(ValueError, match=rf"^model {re.escape(name)}, weight set 1: LQ DARE"):
        design_bank(cfg)
