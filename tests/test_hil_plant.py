"""The emulated rig's nonlinear quarter car + servo-hydraulics (hil/sim/plant.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from controller.config import default_config
from controller.plant import linear_model, static_equilibrium, tire_damping_ns_per_m, tire_force_n
from hil.sim.hydraulics import max_force_n, no_load_velocity_mps
from hil.sim.plant import PlantParams, RigPlant, derivatives

CFG = default_config()
DT = 1e-3


def _jacobian(plant: RigPlant, x0: np.ndarray) -> np.ndarray:
    """Central-difference Jacobian of the mechanical states (bypass open, P = 0)."""
    J = np.zeros((4, 4))
    dy_p, dy_m = np.zeros(7), np.zeros(7)
    for i in range(4):
        h = 1e-7 * max(1.0, abs(x0[i]))
        yp, ym = np.zeros(7), np.zeros(7)
        yp[:4], ym[:4] = x0, x0
        yp[i] += h
        ym[i] -= h
        derivatives(yp, plant.p, 0.0, True, 0.0, dy_p)
        derivatives(ym, plant.p, 0.0, True, 0.0, dy_m)
        J[:, i] = (dy_p[:4] - dy_m[:4]) / (2 * h)
    return J


def _tangent_model(cfg=CFG):
    x2 = static_equilibrium(cfg)[1]
    kt = cfg.tire.stiffness_exponent * tire_force_n(x2, cfg.tire) / x2   # d f_k / d x2
    return linear_model(cfg.vehicle, kt, tire_damping_ns_per_m(x2, cfg.tire))


def test_static_equilibrium_matches_closed_form() -> None:
    plant = RigPlant(CFG)
    np.testing.assert_allclose(plant.state[:4], static_equilibrium(CFG), rtol=1e-12)
    assert plant.state[1] == pytest.approx(0.0247, abs=0.0002)     # ~24.7 mm
    for _ in range(2000):
        plant.advance(DT, 0.0, True, 0.0, 0.0)
    np.testing.assert_allclose(plant.state[:4], static_equilibrium(CFG), atol=1e-12)
    r, f, a = plant.true_signals()
    assert abs(r) < 1e-12 and f == 0.0 and abs(a) < 1e-9
    assert plant.tire_force_n == pytest.approx((500 + 60) * CFG.vehicle.gravity_mps2)


def test_jacobian_matches_tangent_linear_model() -> None:
    plant = RigPlant(CFG)
    J = _jacobian(plant, plant.state[:4].copy())
    lm = _tangent_model()
    np.testing.assert_allclose(J, lm.A, rtol=1e-5, atol=1e-6)
    ev_nl = np.sort_complex(np.linalg.eigvals(J))
    ev_lin = np.sort_complex(np.linalg.eigvals(lm.A))
    np.testing.assert_allclose(ev_nl, ev_lin, rtol=1e-5)


def test_small_free_response_follows_linear_model() -> None:
    """A 0.2 mm body displacement decays as expm(A t) of the tangent linear model."""
    plant = RigPlant(CFG)
    eq = plant.state[:4].copy()
    dx0 = np.array([2e-4, 0.0, 0.0, 0.0])
    plant.reset(eq + dx0)
    A = _tangent_model().A
    for k in range(1, 1001):
        plant.advance(DT, 0.0, True, 0.0, 0.0)
        if k % 100 == 0:
            ref = expm(A * k * DT) @ dx0
            np.testing.assert_allclose(plant.state[:4] - eq, ref, atol=2e-3 * 2e-4)


def _undamped(cfg=CFG) -> RigPlant:
    params = PlantParams(suspension_damping_ns_per_m=0.0, tire_damping_scale=0.0)
    return RigPlant(cfg, params)


def _energy_drift(d: np.ndarray, ticks: int = 1500) -> float:
    """Relative energy change of the undamped plant started at equilibrium + d."""
    plant = _undamped()
    plant.reset(plant.state[:4] + d)
    e0 = plant.energy_j()
    scale = max(e0 - RigPlant(CFG).energy_j(), 1e-3)
    for _ in range(ticks):
        plant.advance(DT, 0.0, True, 0.0, 0.0)
    return abs(plant.energy_j() - e0) / scale


def test_integrator_conserves_energy_smooth_motion() -> None:
    """No lift-off, no bump stop: RK4 at 50 us conserves energy to round-off level."""
    assert _energy_drift(np.array([0.01, 0.0, 0.1, 0.0])) < 1e-10


@settings(max_examples=15, deadline=None)
@given(dx1=st.floats(-0.05, 0.05), dx2=st.floats(-0.03, 0.02), v3=st.floats(-0.5, 0.5),
       v4=st.floats(-1.0, 1.0))
def test_integrator_conserves_energy_without_damping(dx1: float, dx2: float, v3: float,
                                                     v4: float) -> None:
    """Any motion, including wheel lift-off (x2 <= 0) and bump-stop contact, whose kinks
    cost RK4 its order locally: still conserved to 1e-5 of the motion's energy."""
    assert _energy_drift(np.array([dx1, dx2, v3, v4])) < 1e-5


def test_energy_decreases_monotonically_with_damping() -> None:
    plant = RigPlant(CFG)
    plant.reset(plant.state[:4] + np.array([0.04, 0.01, 0.0, 0.5]))
    energies = [plant.energy_j()]
    for _ in range(3000):
        plant.advance(DT, 0.0, True, 0.0, 0.0)
        energies.append(plant.energy_j())
    d = np.diff(energies)
    assert np.all(d <= 1e-9)
    assert energies[-1] < energies[0] - 10.0


def test_tire_pushes_never_pulls_and_lift_off_is_flagged() -> None:
    plant = RigPlant(CFG)
    eq = plant.state[:4].copy()
    plant.reset(eq + np.array([0.0, 0.0, 0.0, 2.5]))    # wheel thrown upwards
    tire, off = [], 0.0
    for _ in range(1000):
        plant.advance(DT, 0.0, True, 0.0, 0.0)
        tire.append(plant.tire_force_n)
        off += plant.off_ground_time_last_tick_s
    assert min(tire) >= 0.0
    assert off > 0.005
    assert np.all(np.isfinite(plant.state))


def test_bypass_open_decays_pressure_with_its_time_constant() -> None:
    plant = RigPlant(CFG)
    plant.state[5] = 5e6
    tau = CFG.actuator.bypass_time_constant_s
    plant.advance(DT, 1.0, True, 0.0, 0.0)
    assert plant.load_pressure_pa == pytest.approx(5e6 * math.exp(-DT / tau), rel=1e-6)


def test_spool_is_first_order_and_pressure_is_bounded_by_supply() -> None:
    plant = RigPlant(CFG)
    tau = CFG.actuator.spool_time_constant_s
    plant.advance(DT, 1.0, False, 0.0, 0.0)
    assert plant.spool == pytest.approx(1.0 - math.exp(-DT / tau), rel=1e-6)
    peak = 0.0
    for _ in range(300):
        plant.advance(DT, 1.0, False, 0.0, 0.0)
        peak = max(peak, abs(plant.load_pressure_pa))
    assert peak <= CFG.actuator.supply_pressure_pa * (1 + 1e-12)
    # full command, body pushed up against the spring: force rises towards A Ps
    assert plant.actuator_force_n > 0.3 * max_force_n(CFG.actuator)
    assert plant.hydraulic_power_w >= 0.0


def test_supply_loss_cannot_build_force() -> None:
    plant = RigPlant(CFG)
    plant.set_supply_lost(True)
    for _ in range(300):
        plant.advance(DT, 1.0, False, 0.0, 0.0)
    assert abs(plant.actuator_force_n) < 1.0
    plant.reset()
    assert plant.supply_pressure_pa == CFG.actuator.supply_pressure_pa


def test_no_load_velocity_closed_form() -> None:
    """Free actuator (no pressure build-up): extension rate at full spool = closed form."""
    a = CFG.actuator
    v = no_load_velocity_mps(a)
    dy = np.zeros(7)
    plant = RigPlant(CFG)
    y = plant.state.copy()
    y[4] = 1.0
    y[2] = v          # zs' - zu' = v  -> valve flow balances piston flow, P' = 0
    derivatives(y, plant.p, 1.0, False, 0.0, dy)
    assert abs(dy[5]) < 1e-6 * a.alpha_n_per_m5 * a.piston_area_m2 * v


@pytest.mark.parametrize("alpha", [4.515e11, 4.515e13])
def test_stiff_hydraulics_integrate_stably_and_converge(alpha: float) -> None:
    """A&H's undamped-oil alpha is much stiffer; the substepped RK4 stays accurate."""
    cfg = CFG.replace(actuator={"alpha_n_per_m5": alpha})
    runs = []
    for sub in (20, 80):
        plant = RigPlant(cfg, substeps=sub)
        t = np.arange(400) * DT
        for k in range(400):
            cmd = 0.3 * math.sin(2 * math.pi * 3 * t[k])
            plant.advance(DT, cmd, False, 0.0, 0.0)
        runs.append(plant.state.copy())
    assert np.all(np.isfinite(runs[0]))
    np.testing.assert_allclose(runs[0][:4], runs[1][:4], rtol=1e-4, atol=1e-8)
    assert runs[0][5] == pytest.approx(runs[1][5], rel=1e-3, abs=10.0)


def test_params_override_and_bad_numbers_never_raise() -> None:
    plant = RigPlant(CFG, PlantParams(sprung_mass_kg=550.0, tire_stiffness_scale=1.1))
    load = (550.0 + 60.0) * CFG.vehicle.gravity_mps2
    x2 = (load / (85.0 * 1.1)) ** (1 / 1.3) / 1000
    assert plant.state[1] == pytest.approx(x2, rel=1e-12)
    plant.advance(DT, math.nan, False, math.nan, math.inf)    # sanitised
    assert not plant.nonfinite and plant.bypass_open
    plant.state[2] = math.nan
    plant.advance(DT, 0.0, True, 0.0, 0.0)
    assert plant.nonfinite
    with pytest.raises(ValueError):
        RigPlant(CFG, PlantParams(sprung_mass_kg=-1.0))


def test_road_height_is_tracked_without_drift() -> None:
    plant = RigPlant(CFG)
    h = 0.01 * np.sin(np.linspace(0, 20, 1001))
    for k in range(1000):
        plant.advance(DT, 0.0, True, h[k], (h[k + 1] - h[k]) / DT)
    assert plant.state[6] == pytest.approx(h[1000], abs=1e-12)
