"""Sprung-mass estimator (controller/mass_estimator.py, docs/design.md §10): the kernel
is the plain recursion, the fit is exact on data that obey the body equation, it holds on
a quiet rig, and in closed loop on the thesis course it finds the mass of the emulated rig
and follows a ballast change."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from controller.config import ConfigError, default_config
from controller.design import bump_stop_input
from controller.mass_estimator import MassEstimator, mass_estimator_parameters
from controller.runtime.bank import BankRuntime
from hil.sim.closed_loop import cached_design, simulate
from hil.sim.roads import make_road

CFG = default_config()
V = CFG.vehicle
_, _STOP_LO, _STOP_HI = bump_stop_input(CFG)
STOPS = (float(_STOP_LO), float(_STOP_HI))      # rebound, compression stop readings [m]
DT = CFG.sample_time_s
COURSE_SPEED_MPS = 11.176


def _body_data(mass_kg: float, n: int, seed: int, offset_n: float = 0.0,
               spring_scale: float = 1.0, damping_scale: float = 1.0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(force [N], LVDT [m], acceleration [m/s^2]) that obey M a = F + K z + C z' exactly
    at the mid-tick instants (z' the backward difference, a, F and z the mean of two
    samples), z band-limited random motion; K and C the configured ones x the scales;
    ``offset_n``: a constant force (a ballast's weight before the LVDT is re-zeroed, a
    load-cell offset)."""
    rng = np.random.default_rng(seed)
    b, a = signal.butter(2, [0.5, 5.0], btype="bandpass", fs=1.0 / DT)
    z = 0.01 * signal.lfilter(b, a, rng.standard_normal(n)) / 0.05
    zdot = np.diff(z, prepend=z[0]) / DT
    acc = 0.5 * signal.lfilter(b, a, rng.standard_normal(n)) / 0.05
    # mid-tick force from the mid-tick terms, then samples whose pairwise means are it
    k = V.suspension_stiffness_n_per_m * spring_scale
    c = V.suspension_damping_ns_per_m * damping_scale
    z_mid = 0.5 * (z + np.concatenate(([z[0]], z[:-1])))
    a_mid = 0.5 * (acc + np.concatenate(([acc[0]], acc[:-1])))
    f_mid = mass_kg * a_mid - k * z_mid - c * zdot - offset_n
    force = np.empty(n)
    force[0] = f_mid[0]
    for i in range(1, n):
        force[i] = 2.0 * f_mid[i] - force[i - 1]
    return force, z, acc


def test_fit_is_exact_on_the_body_equation_despite_a_constant_offset() -> None:
    est = MassEstimator(mass_estimator_parameters(CFG, STOPS))
    force, z, acc = _body_data(380.0, 20_000, seed=1, offset_n=1500.0)
    for f, r, a in zip(force, z, acc, strict=True):
        est.step(f, r, a)
    assert est.estimate_kg == pytest.approx(380.0, rel=1e-3)


def test_fit_finds_mass_spring_and_damper_of_a_rig_unlike_the_configured_one() -> None:
    """K 0.7 x and C 1.4 x the configured ones (a 25 % spread draws such rigs): the fit of
    [M, K, C] finds all three, where a fit of M alone with the configured K and C would
    be off by tens of per cent (the weak prior on K and C moves them < 0.5 %)."""
    est = MassEstimator(mass_estimator_parameters(CFG, STOPS))
    force, z, acc = _body_data(540.0, 20_000, seed=5, offset_n=-800.0, spring_scale=0.7,
                               damping_scale=1.4)
    for f, r, a in zip(force, z, acc, strict=True):
        est.step(f, r, a)
    assert est.estimate_kg == pytest.approx(540.0, rel=5e-3)
    assert est.spring_rate_n_per_m == pytest.approx(0.7 * V.suspension_stiffness_n_per_m,
                                                    rel=5e-3)
    assert est.damping_ns_per_m == pytest.approx(1.4 * V.suspension_damping_ns_per_m,
                                                 rel=5e-3)


def test_kernel_is_the_plain_recursion() -> None:
    """The bank's estimate (numba kernel, fed the load-cell force plus the bump-stop force
    it computes) equals :class:`MassEstimator` on the same readings, tick by tick."""
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    ref = MassEstimator(mass_estimator_parameters(CFG, STOPS))
    force, z, acc = _body_data(620.0, 6000, seed=2)
    got, want = [], []
    for f, r, a in zip(force, z, acc, strict=True):
        rt.step(r, a, f)
        got.append(rt.sprung_mass_est_kg)
        want.append(ref.step(f + rt.bump_stop_force, r, a))
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert got[-1] == pytest.approx(620.0, rel=1e-2)
    assert rt.spring_rate_est_n_per_m == pytest.approx(ref.spring_rate_n_per_m, rel=1e-9)
    assert rt.damping_est_ns_per_m == pytest.approx(ref.damping_ns_per_m, rel=1e-9)
    assert rt.counters()["mass_estimate_updates"] == ref.updates > 0
    rt.reset()
    assert rt.sprung_mass_est_kg == V.sprung_mass_kg
    assert rt.spring_rate_est_n_per_m == V.suspension_stiffness_n_per_m
    assert rt.counters()["mass_estimate_updates"] == 0


def test_quiet_rig_holds_the_estimate_and_off_is_the_configured_mass() -> None:
    est = MassEstimator(mass_estimator_parameters(CFG, STOPS))
    force, z, acc = _body_data(430.0, 10_000, seed=3)
    for f, r, a in zip(force, z, acc, strict=True):
        est.step(f, r, a)
    held = est.estimate_kg
    rng = np.random.default_rng(4)              # at rest: sensor noise only, wrong "force"
    counts = []
    for _ in range(2):      # the old information fades below the gate, then nothing updates
        for _ in range(30_000):
            est.step(200.0 * rng.standard_normal(), 5e-5 * rng.standard_normal(),
                     0.01 * rng.standard_normal())
        counts.append(est.updates)
    assert counts[1] == counts[0]
    assert est.estimate_kg == pytest.approx(held, rel=0.02)   # 40 x the load-cell noise
    off = MassEstimator(mass_estimator_parameters(
        CFG.replace(design={"mass_estimator_window_s": 0.0}), STOPS))
    for f, r, a in zip(force, z, acc, strict=True):
        off.step(f, r, a)
    assert off.estimate_kg == V.sprung_mass_kg and off.updates == 0


def test_bad_band_names_the_key() -> None:
    for band in ([2.0, 1.0], [0.0, 5.0], [1.0, 400.0], [1.0]):
        with pytest.raises(ConfigError, match=r"design\.mass_estimator_band_hz"):
            CFG.replace(design={"mass_estimator_band_hz": band})


def _estimate_run(emulator: dict[str, float], duration_s: float, controller: str = "fuzzy"
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    road = make_road("rough-course", COURSE_SPEED_MPS, duration_s, DT, 1)
    res = simulate(CFG.replace(emulator=emulator), road, controller, 1, seed=1,
                   design=cached_design(CFG))
    return res.traces["sprung_mass_est_kg"], res.traces["sprung_mass_kg"], res.metrics


def test_estimate_within_5_percent_after_10_s_on_the_thesis_course() -> None:
    """Emulated rig 0.7 x the configured mass, the controller designed for 1.0 x."""
    est, true, metrics = _estimate_run({"sprung_mass_scale": 0.7}, 12.0)
    assert np.all(true == pytest.approx(0.7 * V.sprung_mass_kg))
    err = np.abs(est / true - 1.0)
    assert err[round(10.0 / DT):].max() < 0.05
    assert err[0] == pytest.approx(1.0 / 0.7 - 1.0)      # it started from the configured mass
    assert metrics["sprung_mass_est_ratio"] == pytest.approx(1.0, abs=0.05)


def test_estimate_within_5_percent_on_a_rig_with_another_spring_and_damper() -> None:
    """The emulated rig 0.8 x the configured mass on a spring 0.8 x and a damper 1.3 x the
    configured ones: the mass within 5 % after 10 s (a fit of M alone with the configured
    K and C read this rig's 400 kg as 296 kg)."""
    est, true, _ = _estimate_run({"sprung_mass_scale": 0.8, "spring_rate_scale": 0.8,
                                  "damping_scale": 1.3}, 12.0)
    err = np.abs(est / true - 1.0)
    assert err[round(10.0 / DT):].max() < 0.05


def test_estimate_follows_a_30_percent_ballast_step_within_5_s_without_fault() -> None:
    est, true, metrics = _estimate_run({"ballast_step_time_s": 4.0,
                                        "ballast_step_scale": 1.3}, 9.5)
    k = round(4.0 / DT)
    assert true[k - 1] == V.sprung_mass_kg and true[k + 1] == pytest.approx(
        1.3 * V.sprung_mass_kg)
    err = np.abs(est / true - 1.0)
    assert err[k - round(1.0 / DT):k - 1].max() < 0.05
    assert err[k + 1] > 0.2                        # the step is news to the estimator
    assert err[k + round(5.0 / DT):].max() < 0.05
    assert metrics["n_faults"] == 0


def test_passive_run_has_no_estimate() -> None:
    road = make_road("rough-course", COURSE_SPEED_MPS, 0.5, DT, 1)
    res = simulate(CFG, road, "passive", seed=1)
    assert np.all(np.isnan(res.traces["sprung_mass_est_kg"]))
    assert "sprung_mass_est_ratio" not in res.metrics


def test_an_isolated_stop_contact_whose_force_is_off_does_not_move_the_fit() -> None:
    """The bump-stop force is known only to the stops' geometry: one contact whose force
    is 3 kN off (a 3 mm error at 1 MN/m) would throw the band-passed fit for a second.
    The fit takes no data from a reading near a stop until the band-pass has forgotten
    it, while contacts are rare; when they are not (``contacts_rare`` False: a rig that
    lives on a stop), it takes them."""
    force, z, acc = _body_data(560.0, 12_000, seed=12)
    peak = np.abs(z).max()
    stops = (-(peak - 0.001), peak - 0.001)                  # one excursion beyond these
    beyond = np.abs(z) > peak - 0.001
    contact = np.flatnonzero(beyond)
    assert contact.size < 20 and contact[-1] - contact[0] < 20
    k = int(contact[0])                                      # (8.6 s in: the fit is settled)
    wrong = force + np.where(beyond, 3000.0, 0.0)            # its stop force 3 kN off
    err = {}
    for rare in (True, False):
        est = MassEstimator(mass_estimator_parameters(CFG, stops))
        trace = [est.step(f, r, a, contacts_rare=rare) for f, r, a in zip(wrong, z, acc,
                                                                         strict=True)]
        err[rare] = np.abs(np.array(trace[k:k + 1_500]) / 560.0 - 1.0).max()
        assert trace[k - 1] == pytest.approx(560.0, rel=1e-3)
    assert err[True] < 0.005 and err[False] > 0.02, err


def test_kernel_holds_the_fit_like_the_reference_at_stop_contacts() -> None:
    """Readings that reach the stops: the kernel (its stop-contact window deciding whether
    contacts are rare, the tick before) is :class:`MassEstimator` tick by tick."""
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    ref = MassEstimator(mass_estimator_parameters(CFG, STOPS))
    force, z, acc = _body_data(620.0, 8000, seed=7)
    z = z * 0.09 / np.abs(z).max()                  # peaks 10 mm into a stop
    budget = CFG.safety.stop_contact_budget_s
    got, want, rare = [], [], []
    for f, r, a in zip(force, z, acc, strict=True):
        rare.append(rt.stop_contact_s < budget)
        rt.step(r, a, f)
        got.append(rt.sprung_mass_est_kg)
        want.append(ref.step(f + rt.bump_stop_force, r, a, contacts_rare=rare[-1]))
    assert (np.abs(z) > STOPS[1]).sum() > 0 and not all(rare) and any(rare)
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_a_single_contact_with_the_ride_height_off_leaves_the_estimate() -> None:
    """5 % Monte Carlo plant 8 (study seed 11: M 513 kg, ride height 3.3 mm off the
    calibrated centre), weight set 2: its one stop contact (14.8 s) took the estimate from
    516 to 657 kg, and 575 kg 5 s later; it now stays within 5 %.  (The stop clamp keeps
    this plant off the stop: it is off here, to have the contact.)"""
    from hil.sim.montecarlo import draw_params

    params = draw_params(CFG, 20, 0.05, seed=11)[8]
    road = make_road("rough-course", COURSE_SPEED_MPS, 20.0, DT, 1)
    cfg = CFG.replace(design={"preview_stop_clamp_m": 0.0})
    res = simulate(cfg, road, "fuzzy", 2, params=params, seed=1008, design=cached_design(CFG))
    t = res.traces["time_s"]
    err = np.abs(res.traces["sprung_mass_est_kg"] / res.traces["sprung_mass_kg"] - 1.0)
    assert res.metrics["bump_stop_time_s"] > 0.0            # it does touch a stop
    assert err[t > 10.0].max() < 0.05
