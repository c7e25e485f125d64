"""Valve flow feedforward of the force loop (controller/actuator.py, docs/design.md 7).

Independent references: the emulator's valve law (``hil/sim/hydraulics.py``) for the flow the
feedforward must supply at any load pressure; scipy's ``lfilter`` for the rate filter;
the continuous closed form of the linearised actuator under the PI for the apparent
damping it leaves; the plain-Python ``FlowFeedforward`` against its numba twin in the bank
kernel; the nonlinear emulated rig for the zero-force run.
"""

from __future__ import annotations

import math
import warnings

import control
import numpy as np
import pytest
import scipy.linalg
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.actuator import FlowFeedforward, flow_feedforward, servo_model
from controller.config import ConfigError, default_config
from controller.design import design_bank
from controller.margins import connect, force_loop_ss
from controller.runtime.bank import BankRuntime
from controller.runtime.force_loop import PIForceLoop
from controller.runtime.kernels import F_PEND, Blending
from hil.sim.hydraulics import load_pressure_rate, valve_flow_term

CFG = default_config()
DT = CFG.sample_time_s
ACT = CFG.actuator
FF = flow_feedforward(CFG)


def test_gain_is_the_valve_flow_closed_form() -> None:
    """c = g alpha A / (gamma x_s sqrt(Ps)) = g k_h / kq; filter a = 1 - e^{-2 pi fc T}."""
    c = ACT.alpha_n_per_m5 * ACT.piston_area_m2 / (
        ACT.valve_gamma * ACT.spool_stroke_m * math.sqrt(ACT.supply_pressure_pa))
    assert FF.gain_s_per_m == pytest.approx(c, rel=1e-12)
    sv = servo_model(CFG)
    assert FF.gain_s_per_m == pytest.approx(sv.hydraulic_stiffness_n_per_m
                                            / sv.flow_gain_n_per_s, rel=1e-12)
    fc = CFG.force_loop.rattle_rate_lowpass_hz
    assert FF.rate_filter_coeff == pytest.approx(1.0 - math.exp(-2 * math.pi * fc * DT))
    half = flow_feedforward(CFG.replace(force_loop={"flow_feedforward_gain": 0.5}))
    assert half.gain_s_per_m == pytest.approx(0.5 * c, rel=1e-12)
    assert flow_feedforward(CFG.replace(force_loop={"flow_feedforward_gain": 0.0})
                            ).spool(0.3, 0.0) == 0.0


def test_rate_filter_is_a_low_passed_backward_difference() -> None:
    """rho = lfilter(b (1 - z^-1) / (1 - (1 - a) z^-1)) of the LVDT samples, starting at
    rest on the first sample; s_ff = c (-rho) / sqrt(drop)."""
    rng = np.random.default_rng(5)
    r = np.cumsum(rng.normal(0.0, 2e-4, 500)) + 0.01
    b, a = FF.rate_input_gain_per_s, FF.rate_filter_coeff
    rho_ref = scipy.signal.lfilter([b, -b], [1.0, -(1.0 - a)], r - r[0])
    w = FF.initial_state(float(r[0]))
    spool = np.zeros(r.size)
    for k, x in enumerate(r):
        spool[k], w = FF.step(w, float(x), 0.0)
    np.testing.assert_allclose(spool, -FF.gain_s_per_m * rho_ref, rtol=1e-9, atol=1e-12)
    assert spool[0] == 0.0


@pytest.mark.parametrize("force_n", [-8000.0, -3000.0, 0.0, 3000.0, 8000.0])
@pytest.mark.parametrize("v_mps", [-0.4, -0.05, 0.05, 0.4])
def test_feedforward_supplies_the_piston_flow_at_any_load(force_n: float, v_mps: float
                                                          ) -> None:
    """Steady extension at v: the spool the feedforward commands makes the emulator's
    valve pass exactly alpha A v at load pressure F / A (sqrt law), so the flow terms of
    P' cancel and only the leakage is left."""
    ramp = -v_mps * DT * np.arange(300)             # r = zu - zs falls when extending
    w = FF.initial_state(float(ramp[0]))
    spool = 0.0
    for x in ramp:
        spool, w = FF.step(w, float(x), force_n)
    p = force_n / ACT.piston_area_m2
    x_s = ACT.spool_stroke_m * spool
    want = ACT.alpha_n_per_m5 * ACT.piston_area_m2 * v_mps
    got = valve_flow_term(x_s, p, ACT.supply_pressure_pa, ACT.valve_gamma)
    assert got == pytest.approx(want, rel=1e-9)
    rate = load_pressure_rate(p, x_s, v_mps, ACT.piston_area_m2, ACT.supply_pressure_pa,
                              ACT.alpha_n_per_m5, ACT.leakage_beta_per_s, ACT.valve_gamma,
                              False, ACT.bypass_time_constant_s)
    assert rate == pytest.approx(-ACT.leakage_beta_per_s * p, abs=1e-6 * abs(want))


def test_pressure_drop_floor_bounds_the_spool_near_stall() -> None:
    stall = FF.stall_force_n
    floor = FF.min_pressure_drop_fraction
    v = 0.2
    assert FF.spool(v, 2.0 * stall) == pytest.approx(FF.gain_s_per_m * v / math.sqrt(floor))
    assert FF.spool(-v, -2.0 * stall) == pytest.approx(-FF.gain_s_per_m * v / math.sqrt(floor))
    # flow against the load gets the larger drop: less spool
    assert abs(FF.spool(-v, 0.5 * stall)) < abs(FF.spool(v, 0.5 * stall))


def test_config_keys_are_validated_by_name() -> None:
    for key, bad in (("flow_feedforward_gain", -0.1), ("flow_feedforward_gain", 2.0),
                     ("rattle_rate_lowpass_hz", 0.0),
                     ("min_pressure_drop_fraction", 0.0)):
        with pytest.raises(ConfigError, match=f"force_loop.{key}"):
            CFG.replace(force_loop={key: bad})
    with pytest.raises(ValueError, match="rate_filter_coeff"):
        FlowFeedforward(0.3, 0.0, DT, 1e4, 0.1)


def test_force_loop_is_the_pi_plus_the_feedforward() -> None:
    """PIForceLoop with the feedforward = the plain PI + FlowFeedforward.step, tick by
    tick (unsaturated); the filter restarts at rest after reset()."""
    rng = np.random.default_rng(2)
    n = 300
    fref = 500.0 * np.sin(np.arange(n) * 0.03)
    fm = fref + rng.normal(0.0, 50.0, n)
    r = np.cumsum(rng.normal(0.0, 3e-4, n))
    with_ff = PIForceLoop.from_config(CFG)
    plain = PIForceLoop(CFG.force_loop, DT, None)
    w = FF.initial_state(float(r[0]))
    for k in range(n):
        ff, w = FF.step(w, float(r[k]), float(fm[k]))
        got = with_ff.step(float(fref[k]), float(fm[k]), float(r[k]))
        want = plain.step(float(fref[k]), float(fm[k]), 0.0) + ff
        assert abs(want) < CFG.force_loop.output_limit
        assert got == pytest.approx(want, rel=1e-12, abs=1e-15)
        assert with_ff.feedforward_spool == ff
    with_ff.reset()
    with_ff.step(0.0, 0.0, 0.05)
    assert with_ff.feedforward_spool == 0.0
    state = with_ff.rate_state_mps
    assert with_ff.step(0.0, 0.0, math.nan) == 0.0
    assert with_ff.rate_state_mps == state


def test_force_loop_rejects_a_feedforward_for_another_rate() -> None:
    with pytest.raises(ValueError, match="dt"):
        PIForceLoop(CFG.force_loop, 2e-3, FF)


@pytest.fixture(scope="module")
def bank_and_pi() -> tuple[BankRuntime, PIForceLoop]:
    cfg = CFG.replace(force_loop={"ki_per_ns": 0.0})   # the spool model has no integral
    rt = BankRuntime(design_bank(cfg), blending=Blending.LQG, weight_set=1, cfg=cfg)
    return rt, PIForceLoop.from_config(cfg)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.05, 0.05), st.floats(-20.0, 20.0),
                          st.floats(-9000.0, 9000.0)), min_size=2, max_size=60))
def test_bank_spool_model_is_the_force_loop(bank_and_pi: tuple[BankRuntime, PIForceLoop],
                                            seq: list[tuple[float, float, float]]) -> None:
    """The bank's own spool model (numba ``servo_update``) computes the spool command the
    force loop (plain Python) sends for the bank's output, incl. the sqrt pressure law
    and clipping: the command pending for the valve after each tick (D = 1)."""
    rt, pi = bank_and_pi
    assert rt.design.compute_delay_ticks == 1
    rt.reset()
    pi.reset()
    for r, a, f in seq:
        out = rt.step(r, a, f)
        sent = pi.step(out, f, r)
        assert rt._fv[F_PEND] == pytest.approx(sent, rel=1e-12, abs=1e-14)


def _apparent_damping(gain: float, freqs_hz: np.ndarray) -> np.ndarray:
    """F / v of the linearised actuator (ZOH, discrete) under the force loop at zero force
    reference, piston extension rate v as the input: complex [N s/m]."""
    cfg = CFG.replace(force_loop={"flow_feedforward_gain": gain})
    sv = servo_model(cfg)
    tau, kq, kh = sv.spool_time_constant_s, sv.flow_gain_n_per_s, sv.hydraulic_stiffness_n_per_m
    # states [x_v, F, r] (r' = -v), inputs [s, v]
    M = np.zeros((5, 5))
    M[:3, :3] = [[-1.0 / tau, 0.0, 0.0], [kq, -sv.leakage_per_s, 0.0], [0.0, 0.0, 0.0]]
    M[:3, 3:] = [[1.0 / tau, 0.0], [0.0, -kh], [0.0, -1.0]]
    E = scipy.linalg.expm(M * DT)
    act = control.ss(E[:3, :3], E[:3, 3:], [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], np.zeros((2, 2)),
                     DT, inputs=["s", "v"], outputs=["Fm", "r"], name="act")
    zero = control.ss([], [], [], [[0.0]], DT, inputs=["z"], outputs=["fref"], name="zero")
    pi = force_loop_ss(cfg.force_loop, flow_feedforward(cfg), DT)
    pi = control.ss(pi.A, pi.B, pi.C, pi.D, DT, inputs=["fref", "Fm", "r"], outputs=["s"],
                    name="pi")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sys = connect([act, pi, zero], ["v", "z"], ["Fm"])
    z = np.exp(1j * 2 * np.pi * freqs_hz * DT)
    return np.array([complex(sys(zi)[0, 0]) for zi in z])


def test_feedforward_makes_the_closed_actuator_transparent() -> None:
    """Without the feedforward the PI leaves the oil column as a 2-3 kNs/m damper between
    3 and 15 Hz (the continuous closed form k_h / (jw + beta + kq (kp + ki/jw) / (1 + jw
    tau)) agrees); with it the apparent damping drops to a quarter or less."""
    f = np.array([3.0, 5.0, 8.0, 12.0, 15.0])
    sv = servo_model(CFG)
    fl = CFG.force_loop
    jw = 1j * 2 * np.pi * f
    closed = -sv.hydraulic_stiffness_n_per_m / (
        jw + sv.leakage_per_s + sv.flow_gain_n_per_s * (fl.kp_per_n + fl.ki_per_ns / jw)
        / (1.0 + jw * sv.spool_time_constant_s))
    off = _apparent_damping(0.0, f)
    np.testing.assert_allclose(np.abs(off), np.abs(closed), rtol=0.12)
    assert np.all((np.abs(off) > 2.0e3) & (np.abs(off) < 3.3e3))
    on = _apparent_damping(1.0, f)
    assert np.all(np.abs(on) < 0.25 * np.abs(off))
    assert abs(_apparent_damping(1.0, np.array([0.5]))[0]) < 20.0


def test_zero_force_run_costs_about_passive_on_the_rough_course() -> None:
    """Nonlinear emulated rig, 10 s rough course at 25 mph: force reference 0 with the
    valve closed is within 5 % of passive with the feedforward, ~3x passive without."""
    from hil.sim.closed_loop import simulate
    from hil.sim.roads import make_road

    road = make_road("rough-course", 11.176, 10.0, DT, 1)
    passive = simulate(CFG, road, "passive", seed=1).metrics["absorbed_power"]
    on = simulate(CFG, road, "zero-force", seed=1).metrics
    off = simulate(CFG.replace(force_loop={"flow_feedforward_gain": 0.0}), road,
                   "zero-force", seed=1).metrics
    assert on["n_faults"] == 0.0 and on["unstable"] == 0.0
    assert on["absorbed_power"] < 1.05 * passive
    assert off["absorbed_power"] > 2.0 * passive
