"""PI force inner loop: closed-loop response against scipy, anti-windup, fault handling
(the plain PI, ``feedforward=None``; the flow feedforward is tested in
tests/test_flow_feedforward.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import ForceLoopConfig, default_config
from controller.runtime.force_loop import PIForceLoop
from controller.runtime.kernels import StepFlag

GAIN_N = 10_000.0      # first-order actuator: F' = (GAIN_N * spool - F) / TAU
TAU_S = 0.003
#: gains for the toy static-gain actuator above (the defaults are tuned for the rig's
#: integrating servo-hydraulics, controller/margins.py; on this toy plant they settle
#: slowly, which is not what these mechanics tests are about)
TOY_GAINS = dataclasses.replace(default_config().force_loop, kp_per_n=2e-4, ki_per_ns=0.05)


def _sim_pi(cfg: ForceLoopConfig, dt: float, ref: np.ndarray, *, naive: bool = False,
            blocked: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """PI (or a naive PI without anti-windup) driving the exact-ZOH first-order actuator;
    where ``blocked`` the actuator produces no force (bypass open, valve still driven)."""
    a = math.exp(-dt / TAU_S)
    pi = PIForceLoop(cfg, dt, None)
    force = 0.0
    integ = 0.0
    f_out, s_out = np.zeros(ref.size), np.zeros(ref.size)
    for k, r in enumerate(ref):
        f_out[k] = force
        if naive:
            e = min(max(r, -cfg.force_limit_n), cfg.force_limit_n) - force
            integ += e * dt
            s = min(max(cfg.kp_per_n * e + cfg.ki_per_ns * integ, -cfg.output_limit),
                    cfg.output_limit)
        else:
            s = pi.step(r, force, 0.0)
        s_out[k] = s
        gain = 0.0 if blocked is not None and blocked[k] else GAIN_N
        force = a * force + (1.0 - a) * gain * s
    return f_out, s_out


def test_step_response_matches_exact_discrete_closed_loop() -> None:
    """PI + ZOH first-order actuator vs the closed loop built as a state space (dlsim)."""
    cfg = default_config().force_loop
    dt = 1e-3
    kp, ki = cfg.kp_per_n, cfg.ki_per_ns
    a = math.exp(-dt / TAU_S)
    b = (1.0 - a) * GAIN_N
    # state z = [F_k, I_{k-1}], input r:  I_k = I_{k-1} + (r - F_k) dt,
    # s_k = kp (r - F_k) + ki I_k,  F_{k+1} = a F_k + b s_k
    s_z = np.array([-kp - ki * dt, ki])
    s_r = kp + ki * dt
    A = np.array([[a + b * s_z[0], b * s_z[1]], [-dt, 1.0]])
    B = np.array([[b * s_r], [dt]])
    C = np.array([[1.0, 0.0]])
    n = 300
    ref = np.full(n, 1000.0)
    _, yd, _ = scipy.signal.dlsim((A, B, C, np.zeros((1, 1)), dt), ref[:, None])
    f_out, s_out = _sim_pi(cfg, dt, ref)
    assert np.max(np.abs(s_out)) < cfg.output_limit      # linear regime
    np.testing.assert_allclose(f_out, yd[:, 0], rtol=1e-9, atol=1e-9)


def test_step_response_matches_continuous_closed_loop() -> None:
    """At a fine sample time the loop approaches the continuous PI closed loop
    F/F_ref = G (kp s + ki) / (tau s^2 + (1 + G kp) s + G ki)."""
    cfg = TOY_GAINS
    dt = 1e-5
    t = np.arange(0.0, 0.1, dt)
    ref = np.full(t.size, 1000.0)
    f_out, _ = _sim_pi(cfg, dt, ref)
    G, kp, ki = GAIN_N, cfg.kp_per_n, cfg.ki_per_ns
    sys = scipy.signal.lti([G * kp, G * ki], [TAU_S, 1.0 + G * kp, G * ki])
    _, yc = scipy.signal.step(sys, T=t)
    assert np.max(np.abs(f_out - 1000.0 * yc)) < 0.01 * 1000.0
    assert abs(f_out[-1] - 1000.0) < 5.0        # integral action: no steady-state error


def test_anti_windup_bounds_integrator_and_recovers_fast() -> None:
    cfg = TOY_GAINS
    dt = 1e-3
    # 1 s asking for force the actuator cannot give (blocked: stuck at 0 N)
    pi = PIForceLoop(cfg, dt, None)
    for _ in range(1000):
        s = pi.step(7000.0, 0.0, 0.0)       # actuator stuck at 0 N
        assert s == pytest.approx(cfg.output_limit)
    assert abs(cfg.ki_per_ns * pi.integral_ns) <= cfg.output_limit + 1e-12
    # blocked and saturated for 1 s, then a reachable reference with a working actuator:
    # compare the recovery with a naive PI (no anti-windup)
    n_sat, n_rec = 1000, 1000
    ref = np.concatenate([np.full(n_sat, 5000.0), np.full(n_rec, 1000.0)])
    blocked = np.arange(ref.size) < n_sat
    f_aw, _ = _sim_pi(cfg, dt, ref, blocked=blocked)
    f_naive, _ = _sim_pi(cfg, dt, ref, naive=True, blocked=blocked)

    def settle_ticks(f: np.ndarray) -> int:
        tail = np.abs(f[n_sat:] - 1000.0) > 50.0
        idx = np.flatnonzero(tail)
        return int(idx[-1]) + 1 if idx.size else 0

    assert settle_ticks(f_aw) < 60                       # < 60 ms to within 5 %
    assert settle_ticks(f_naive) > 3 * settle_ticks(f_aw)


def test_force_reference_is_saturated() -> None:
    cfg = default_config().force_loop
    pi = PIForceLoop(cfg, 1e-3, None)
    pi.step(1e12, 0.0, 0.0)
    assert pi.error_n == pytest.approx(cfg.force_limit_n)
    pi.reset()
    pi.step(-1e12, 0.0, 0.0)
    assert pi.error_n == pytest.approx(-cfg.force_limit_n)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nonfinite_input_returns_zero_and_flags(bad: float) -> None:
    cfg = default_config().force_loop
    pi = PIForceLoop(cfg, 1e-3, None)
    pi.step(500.0, 0.0, 0.0)
    integ = pi.integral_ns
    assert pi.step(bad, 0.0, 0.0) == 0.0
    assert pi.flags == StepFlag.NONFINITE_INPUT
    assert pi.step(100.0, bad, 0.0) == 0.0
    assert pi.step(100.0, 0.0, bad) == 0.0
    assert pi.integral_ns == integ
    pi.step(100.0, 0.0, 0.0)
    assert pi.flags == StepFlag(0)
    pi.reset()
    assert pi.integral_ns == 0.0


def test_bad_sample_time_is_an_error() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        PIForceLoop(default_config().force_loop, 0.0, None)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e15, 1e15), st.floats(-1e15, 1e15),
                          st.floats(-1e3, 1e3)), min_size=1, max_size=50))
def test_output_always_within_limit(seq: list[tuple[float, float, float]]) -> None:
    """With the rig's flow feedforward on (any LVDT reading, any force)."""
    full = default_config()
    cfg = full.force_loop
    pi = PIForceLoop.from_config(full)
    for r, m, x in seq:
        s = pi.step(r, m, x)
        assert math.isfinite(s)
        assert abs(s) <= cfg.output_limit
        assert abs(cfg.ki_per_ns * pi.integral_ns) <= cfg.output_limit * (1 + 1e-12)


_FINITE = st.floats(-5e4, 5e4, allow_nan=False)
_ANY = st.one_of(_FINITE, st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0]))


@settings(max_examples=60, deadline=None)
@given(ticks=st.lists(st.tuples(_ANY, _ANY, st.one_of(st.floats(-0.1, 0.1), _ANY)),
                      min_size=1, max_size=40),
       feedforward=st.booleans(), gains=st.sampled_from(["rig", "toy", "p-only"]),
       reset_at=st.integers(0, 40))
def test_kernel_is_the_plain_python_loop_to_the_bit(
        ticks: list[tuple[float, float, float]], feedforward: bool, gains: str,
        reset_at: int) -> None:
    """The numba step (pi_force_step) against the plain-Python force loop it replaced
    (tests/support/reference_force_loop.py): the same spool command, integrator, rate
    filter, error, feedforward, saturation and flags on every tick, bit for bit, with
    and without the flow feedforward, saturating references, non-finite inputs and a
    reset mid-run."""
    from controller.actuator import flow_feedforward
    from tests.support.reference_force_loop import ReferencePIForceLoop

    cfg = default_config()
    loop_cfg = {"rig": cfg.force_loop, "toy": TOY_GAINS,
                "p-only": dataclasses.replace(TOY_GAINS, ki_per_ns=0.0)}[gains]
    ff = flow_feedforward(cfg) if feedforward else None
    pi = PIForceLoop(loop_cfg, cfg.sample_time_s, ff)
    ref = ReferencePIForceLoop(loop_cfg, cfg.sample_time_s, ff)
    for k, (f_ref, f_meas, r) in enumerate(ticks):
        if k == reset_at:
            pi.reset()
            ref.reset()
        got = pi.step(f_ref, f_meas, r)
        want = ref.step(f_ref, f_meas, r)
        assert math.copysign(1.0, got) == math.copysign(1.0, want) and got == want, k
        for name in ("integral_ns", "error_n", "feedforward_spool"):
            a, b = getattr(pi, name), getattr(ref, name)
            assert a == b and math.copysign(1.0, a) == math.copysign(1.0, b), (k, name)
        w_got, w_want = pi.rate_state_mps, ref.rate_state_mps
        assert w_got == w_want or (math.isnan(w_got) and math.isnan(w_want)), k
        assert (pi.saturated, pi.flags) == (ref.saturated, ref.flags), k
