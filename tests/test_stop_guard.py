"""End-stop guard (controller/stop_guard.py, docs/design.md §9.6): the numba kernel
against the plain-Python law, the law's invariants (with and without the rate lead), the
soft-spring plant it exists for and weight set 2's hard hits on the thesis course that
the lead is for (closed loop on the nonlinear rig)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config, one_layer
from controller.runtime.kernels import (
    F_BS_HI,
    F_BS_LO,
    F_FFB,
    F_FFW,
    F_GUARD_LEAD,
    F_GUARD_S,
    F_GUARD_V0,
    F_GUARD_W,
    F_TS_BETA,
    F_TS_ON,
    FV_HEAD,
    I_GUARD_LEAD_TICKS,
    I_GUARD_TICKS,
    IV_HEAD,
    stop_guard,
)
from controller.stop_guard import stop_guard_scale
from hil.sim.closed_loop import simulate
from hil.sim.plant import PlantParams
from hil.sim.roads import make_road

LO, HI = -0.08, 0.08


def _kernel(u: float, r: float, lo: float, hi: float, w: float, rate: float = 0.0,
            lead: float = 0.0, v0: float = 0.0, beta: float | None = None,
            counts: list[int] | None = None) -> tuple[float, float]:
    """The kernel on a bare parameter vector; the force loop's rate filter holds ``rate``
    (w = rate, b = 0), ``beta`` not None switches the travel schedule on with that share;
    ``counts`` receives the guard's two tick counters."""
    fv = np.zeros(FV_HEAD)
    iv = np.zeros(IV_HEAD, dtype=np.int64)
    fv[F_BS_LO], fv[F_BS_HI], fv[F_GUARD_W] = lo, hi, w
    fv[F_FFW], fv[F_FFB] = rate, 0.0
    fv[F_GUARD_LEAD], fv[F_GUARD_V0] = lead, v0
    if beta is not None:
        fv[F_TS_ON], fv[F_TS_BETA] = 1.0, beta
    out = stop_guard(fv, iv, u, r)
    if counts is not None:
        counts[:] = [int(iv[I_GUARD_TICKS]), int(iv[I_GUARD_LEAD_TICKS])]
    return out, float(fv[F_GUARD_S])


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e4, 1e4), st.floats(-0.2, 0.2), st.floats(-0.1, 0.0),
       st.floats(0.001, 0.1), st.one_of(st.just(0.0), st.floats(1e-6, 0.05)))
def test_kernel_is_the_law_and_only_removes_force_toward_a_stop(
        u: float, r: float, lo: float, span: float, w: float) -> None:
    hi = lo + span
    out, s = _kernel(u, r, lo, hi, w)
    s_ref = stop_guard_scale(u, r, lo, hi, w)
    assert s == pytest.approx(s_ref, rel=1e-12, abs=1e-15)
    assert out == pytest.approx(u * s_ref, rel=1e-12, abs=1e-9)
    assert 0.0 <= s <= 1.0 and abs(out) <= abs(u) and out * u >= 0.0
    if w == 0.0 or (u < 0.0 and hi - r >= w) or (u > 0.0 and r - lo >= w):
        assert out == u                              # outside the zone of the stop ahead
    if w > 0.0 and ((u < 0.0 and r >= hi) or (u > 0.0 and r <= lo)):
        assert out == 0.0                            # at or in the stop it heads for


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e4, 1e4), st.floats(-0.2, 0.2), st.floats(0.001, 0.05),
       st.floats(-5.0, 5.0), st.floats(0.0, 0.1), st.floats(0.0, 2.0),
       st.one_of(st.none(), st.floats(0.0, 1.0)))
def test_kernel_is_the_law_with_the_rate_lead(u: float, r: float, w: float, rate: float,
                                              lead: float, v0: float,
                                              beta: float | None) -> None:
    counts = [0, 0]
    out, s = _kernel(u, r, LO, HI, w, rate, lead, v0, beta, counts)
    lead_eff = lead if beta is None else lead * beta     # schedule: the comfort share
    s_ref = stop_guard_scale(u, r, LO, HI, w, rate, lead_eff, v0)
    s_dist = stop_guard_scale(u, r, LO, HI, w)
    # counted: a tick with force taken away, and of them one where the lead took more
    assert counts == [int(s < 1.0), int(s < s_dist)]
    assert s == pytest.approx(s_ref, rel=1e-12, abs=1e-12)
    assert out == pytest.approx(u * s_ref, rel=1e-12, abs=1e-9)
    assert 0.0 <= s <= 1.0 and abs(out) <= abs(u) and out * u >= 0.0
    # the lead only ever takes more force toward a stop away, never less
    assert s <= stop_guard_scale(u, r, LO, HI, w) + 1e-15
    toward = rate if u < 0.0 else -rate                  # approach rate of the stop ahead
    if toward <= v0 or lead_eff == 0.0:
        assert s == stop_guard_scale(u, r, LO, HI, w)    # within the deadband: the distance law


def test_lead_fades_the_force_earlier_in_a_fast_approach() -> None:
    """The zone moves out by t_lead (r' - v0): at 2 m/s toward the compression stop with
    a 30 ms lead over 0.5 m/s it starts 45 mm further out; the same rate away from that
    stop changes nothing, and the non-finite rate of a filter just reset counts as 0."""
    w, lead, v0 = 0.02, 0.03, 0.5
    shift = lead * (2.0 - v0)
    r = np.linspace(HI - w - shift - 0.01, HI, 501)
    s = np.array([stop_guard_scale(-500.0, x, LO, HI, w, 2.0, lead, v0) for x in r])
    np.testing.assert_allclose(s, np.clip((HI - shift - r) / w, 0.0, 1.0), atol=1e-12)
    assert all(stop_guard_scale(-500.0, x, LO, HI, w, -2.0, lead, v0)
               == stop_guard_scale(-500.0, x, LO, HI, w) for x in r)
    assert stop_guard_scale(-500.0, HI - 0.03, LO, HI, w, float("nan"), lead, v0) == 1.0
    # rebound side, mirrored: the zone's outer edge moves from LO + w to LO + w + shift
    assert stop_guard_scale(500.0, LO + w + 0.01, LO, HI, w) == 1.0
    assert stop_guard_scale(500.0, LO + w + 0.01, LO, HI, w, -2.0, lead, v0) == 0.0
    assert stop_guard_scale(500.0, LO + w + shift - 0.005, LO, HI, w, -2.0, lead, v0) \
        == pytest.approx(0.75, abs=1e-12)
    assert stop_guard_scale(500.0, LO + w + shift, LO, HI, w, -2.0, lead, v0) \
        == pytest.approx(1.0, abs=1e-12)


def test_law_is_continuous_and_linear_across_the_zone() -> None:
    w = 0.02
    r = np.linspace(HI - 1.5 * w, HI + 0.01, 2001)
    s = np.array([stop_guard_scale(-500.0, x, LO, HI, w) for x in r])
    np.testing.assert_allclose(s, np.clip((HI - r) / w, 0.0, 1.0), rtol=0, atol=1e-15)
    assert np.max(np.abs(np.diff(s))) <= (r[1] - r[0]) / w * (1 + 1e-9)
    # a force away from the compression stop is never touched, even inside it
    assert all(stop_guard_scale(500.0, x, LO, HI, w) == 1.0 for x in r)


def test_guard_keeps_a_soft_spring_plant_off_the_stops() -> None:
    """A rig whose spring is 25 % softer than designed (ride height set by preload):
    single LQG with weight set 1 cancels most of the nominal spring between ~0.1 and
    0.5 Hz, the net stiffness there is about zero and the body drifts into the
    compression stop -- over 1.5 s on the stop and a slam (> 10 mm in) without the guard.
    With it the stop contact is a fraction of that and there is no slam (passive: no
    contact at all).  The stop-contact monitor only reports here (with its degrade the
    unguarded run's contact falls to 0.13 s as well: docs/design.md §9.8), and the road
    preview's stop clamp is off (§12: with it the unguarded run does not slam either):
    the guard alone is measured.  The bank has one layer, designed for the nominal
    spring only (the mismatch is the point): a bank with spring-rate layers (0.7 x among
    them) does not drift into the stop even unguarded."""
    base = one_layer(default_config().replace(safety={"stop_contact_degrade": False},
                                              design={"preview_stop_clamp_m": 0.0}))
    prm = PlantParams(ride_height_offset_m=0.0,
                      suspension_stiffness_n_per_m=0.75 * base.vehicle.suspension_stiffness_n_per_m)
    road = make_road("rough-course", 11.176, 20.0, base.sample_time_s, 1)
    runs = {}
    for width in (0.0, 0.02):
        cfg = base.replace(design={"stop_guard_m": width})
        runs[width] = simulate(cfg, road, "lqg", 1, params=prm, seed=3).metrics
    passive = simulate(base, road, "passive", params=prm, seed=3).metrics
    assert passive["bump_stop_time_s"] == 0.0
    off, on = runs[0.0], runs[0.02]
    assert off["bump_stop_slam"] == 1.0 and off["bump_stop_time_s"] > 1.0
    assert on["bump_stop_slam"] == 0.0 and on["bump_stop_time_s"] < 0.2 * off["bump_stop_time_s"]
    assert on["n_faults"] == 0.0 and on["absorbed_power"] < 0.5 * passive["absorbed_power"]


def test_lead_keeps_weight_set_2_off_the_stops_on_the_thesis_course() -> None:
    """Weight set 2's hard hits on the thesis course are fast compressions: the law
    pushes toward the stop (it cancels the damper) and the force loop needs ~20 ms to
    unload, so the distance law fades the force too late.  Road seed 1, 60 s, fuzzy: the
    distance law alone slams (> 10 mm into a stop; passive does not touch it), with the
    default lead there is no slam, less time on the stops and no fault.  Weight set 2
    alone: the travel governor (§12) and the road preview's stop clamp are off, the
    guard alone is measured."""
    base = default_config().replace(design={"govern_comfort_set": False,
                                            "preview_stop_clamp_m": 0.0})
    road = make_road("rough-course", 11.176, 60.0, base.sample_time_s, 1)
    passive = simulate(base, road, "passive", seed=1).metrics
    runs = {lead: simulate(base.replace(design={"stop_guard_lead_s": lead}), road, "fuzzy", 2,
                           seed=1).metrics
            for lead in (0.0, base.design.stop_guard_lead_s)}
    off, on = runs[0.0], runs[base.design.stop_guard_lead_s]
    assert passive["bump_stop_slam"] == 0.0
    assert off["bump_stop_slam"] == 1.0
    assert on["bump_stop_slam"] == 0.0 and on["n_faults"] == 0.0
    assert on["bump_stop_time_s"] < off["bump_stop_time_s"]
    assert on["absorbed_power"] < 0.5 * passive["absorbed_power"]
    # the simulator reports how often the guard and its lead acted
    assert off["stop_guard_lead_fraction"] == 0.0 < off["stop_guard_fraction"]
    assert 0.0 < on["stop_guard_lead_fraction"] <= on["stop_guard_fraction"] < 0.5
