"""``[emulator]``: the emulated rig's true plant may differ from the configuration the
controller is designed from; sim, Monte Carlo and the CAN node all run that plant."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.config import ConfigError, default_config
from hil.sim.closed_loop import simulate
from hil.sim.montecarlo import draw_params
from hil.sim.plant import P_C, P_K, P_KT, P_M, P_m, PlantParams, RigPlant, emulated_params
from hil.sim.roads import make_road

CFG = default_config()
SCALES = {"sprung_mass_scale": 1.12, "spring_rate_scale": 0.92, "damping_scale": 1.10,
          "tire_stiffness_scale": 0.90, "unsprung_mass_scale": 1.05}
OTHER = CFG.replace(emulator=SCALES)


def test_defaults_are_the_configured_rig_bit_for_bit() -> None:
    assert CFG.emulator.is_nominal and emulated_params(CFG) is None
    np.testing.assert_array_equal(RigPlant(CFG).p, RigPlant(CFG, PlantParams()).p)
    assert RigPlant(CFG).static_rattlespace_m == RigPlant(CFG, PlantParams()).static_rattlespace_m
    # Monte Carlo draws with explicit unit scales are the same draws
    unit = CFG.replace(emulator={k: 1.0 for k in SCALES})
    assert draw_params(CFG, 5, 0.1, seed=3) == draw_params(unit, 5, 0.1, seed=3)


def test_scaled_emulator_is_the_true_plant() -> None:
    v = CFG.vehicle
    p = RigPlant(OTHER).p          # what the CAN node and the simulator build by default
    assert p[P_M] == pytest.approx(1.12 * v.sprung_mass_kg)
    assert p[P_m] == pytest.approx(1.05 * v.unsprung_mass_kg)
    assert p[P_K] == pytest.approx(0.92 * v.suspension_stiffness_n_per_m)
    assert p[P_C] == pytest.approx(1.10 * v.suspension_damping_ns_per_m)
    assert p[P_KT] == pytest.approx(0.90 * RigPlant(CFG).p[P_KT])
    # the ride height is set by preload: the static rattlespace stays at the stops' centre
    plant = RigPlant(OTHER)
    eq = plant.equilibrium()
    assert eq[0] - eq[1] == pytest.approx(RigPlant(CFG).static_rattlespace_m, abs=1e-12)


def test_a_softer_heavier_body_rings_slower_as_sqrt_k_over_m() -> None:
    """Passive response to the same bump: the body's ringing frequency scales with
    sqrt(K / M) to within the tire's share of the effective stiffness."""
    road = make_road("bump", 11.176, 4.0, CFG.sample_time_s, 1)
    freqs = []
    for cfg in (CFG, CFG.replace(emulator={"sprung_mass_scale": 1.5,
                                          "spring_rate_scale": 0.7})):
        acc = simulate(cfg, road, "passive", seed=1).traces["accel_mps2"]
        tail = acc[int(1.5 / CFG.sample_time_s):]
        crossings = np.flatnonzero(np.diff(np.signbit(tail - tail.mean())))
        period = 2 * np.median(np.diff(crossings)) * CFG.sample_time_s
        freqs.append(1.0 / period)
    expected = math.sqrt(0.7 / 1.5)
    assert freqs[1] / freqs[0] == pytest.approx(expected, rel=0.15)


def test_monte_carlo_draws_around_the_emulated_rig() -> None:
    v = CFG.vehicle
    cfg = OTHER.replace(emulator={"ride_height_offset_m": 0.004})
    exact = draw_params(cfg, 3, 0.0, seed=1, ride_height_std_m=0.0)
    assert all(p.sprung_mass_kg == pytest.approx(1.12 * v.sprung_mass_kg) for p in exact)
    assert all(p.tire_stiffness_scale == pytest.approx(0.90) for p in exact)
    assert all(p.ride_height_offset_m == pytest.approx(0.004) for p in exact)
    spread = draw_params(cfg, 400, 0.05, seed=2)
    mean_m = np.mean([p.sprung_mass_kg for p in spread])
    assert mean_m == pytest.approx(1.12 * v.sprung_mass_kg, rel=0.01)


def test_bad_emulator_values_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"emulator\.sprung_mass_scale"):
        CFG.replace(emulator={"sprung_mass_scale": 0.0})
    with pytest.raises(ConfigError, match=r"emulator\.lvdt_zero"):
        CFG.replace(emulator={"lvdt_zero": "somewhere"})


BALLAST = CFG.replace(emulator={"ballast_step_time_s": 0.5, "ballast_step_scale": 1.3})


def test_ballast_step_changes_the_mass_once_and_the_body_sags_to_its_new_equilibrium() -> None:
    """+30 % ballast at 0.5 s, passive rig at rest on a flat road: M is the configured one
    until the step and 1.3 x after; the ballast joins at rest (momentum kept); the body
    settles at the new static equilibrium, lower by dM g / K; the LVDT zero stays; a
    reset takes the ballast off."""
    v = CFG.vehicle
    plant = RigPlant(BALLAST)
    assert plant.ballast_step == (0.5, 1.3)
    dt = CFG.sample_time_s
    r_before = plant.rattlespace_m
    zero = plant.static_rattlespace_m
    for _ in range(round(0.5 / dt) - 1):
        plant.advance(dt, 0.0, True, 0.0, 0.0)
    assert plant.sprung_mass_kg == v.sprung_mass_kg
    assert plant.rattlespace_m == pytest.approx(r_before, abs=1e-9)   # at rest before it
    plant.advance(dt, 0.0, True, 0.0, 0.0)
    assert plant.sprung_mass_kg == pytest.approx(1.3 * v.sprung_mass_kg)
    # just after the step the spring still carries the old weight: the body accelerates
    # down by the ballast's weight over the new mass
    assert plant.sprung_accel_mps2 == pytest.approx(-0.3 / 1.3 * v.gravity_mps2, rel=1e-3)
    for _ in range(round(15.0 / dt)):
        plant.advance(dt, 0.0, True, 0.0, 0.0)
    assert plant.sprung_mass_kg == pytest.approx(1.3 * v.sprung_mass_kg)   # once only
    sag = 0.3 * v.sprung_mass_kg * v.gravity_mps2 / v.suspension_stiffness_n_per_m
    assert plant.rattlespace_m - r_before == pytest.approx(sag, rel=1e-3)
    eq = plant.equilibrium()
    assert plant.rattlespace_m == pytest.approx(eq[0] - eq[1], abs=1e-5)
    assert plant.static_rattlespace_m == zero
    assert plant.true_signals()[0] == pytest.approx(sag, rel=1e-3)   # what the LVDT reads
    plant.reset()
    assert plant.sprung_mass_kg == v.sprung_mass_kg
    assert plant.rattlespace_m == pytest.approx(r_before, abs=1e-12)


def test_ballast_step_keeps_momentum() -> None:
    plant = RigPlant(CFG)
    plant.state[2] = 0.2
    plant.change_sprung_mass(2.0 * CFG.vehicle.sprung_mass_kg)
    assert plant.state[2] == pytest.approx(0.1)


def test_ballast_step_reaches_sim_and_monte_carlo() -> None:
    """The same key drives `rig sim` (on top of the emulated plant's own scales) and the
    Monte Carlo's drawn plants; without it nothing changes."""
    assert not CFG.emulator.has_ballast_step and RigPlant(CFG).ballast_step is None
    assert not CFG.replace(emulator={"ballast_step_time_s": 3.0}).emulator.has_ballast_step
    road = make_road("rough-course", 11.176, 4.0, CFG.sample_time_s, 1)
    base = CFG.replace(emulator={"sprung_mass_scale": 0.8})
    cfg = base.replace(emulator={"ballast_step_time_s": 1.0, "ballast_step_scale": 1.3})
    v = CFG.vehicle
    sag = 0.3 * 0.8 * v.sprung_mass_kg * v.gravity_mps2 / v.suspension_stiffness_n_per_m
    for params in (None, draw_params(cfg, 1, 0.05, seed=4)[0]):
        r = simulate(cfg, road, "passive", seed=1, params=params).traces["rattlespace_m"]
        r0 = simulate(base, road, "passive", seed=1, params=params).traces["rattlespace_m"]
        n_step = round(1.0 / CFG.sample_time_s)
        np.testing.assert_array_equal(r[:n_step], r0[:n_step])
        # the body sinks by about the static sag after the step (M, K drawn: +-25 %)
        assert np.mean(r[-1000:] - r0[-1000:]) == pytest.approx(sag, rel=0.25)


def test_bad_ballast_values_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"emulator\.ballast_step_scale"):
        CFG.replace(emulator={"ballast_step_scale": 0.0})
    with pytest.raises(ConfigError, match=r"emulator\.ballast_step_time_s"):
        CFG.replace(emulator={"ballast_step_time_s": -1.0})
