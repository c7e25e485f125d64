"""Stop-contact monitor (controller/stop_contact.py, docs/design.md §9.8): the window
arithmetic of the runtime kernel against its closed form, episodes, degrade / re-arm, the
loop's events, and the monitor on the nonlinear plant."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import ConfigError, default_config
from controller.runtime.bank import BankRuntime
from controller.runtime.kernels import (
    F_BS_HI,
    F_BS_LO,
    F_SC_AUTH,
    F_SC_TIME,
    I_SC_DEG,
    I_SC_EPISODES,
    I_SC_NDEG,
    StepFlag,
    stop_contact,
)
from controller.stop_contact import EPISODE_GAP_S, stop_contact_settings
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop, simulate
from hil.sim.roads import Road, make_road
from rig.service.loop import TICK_RECORD_FIELDS
from rig.telemetry_process.child import snapshot_of
from tests.support.bank_buffers import fresh_buffers
from tests.support.loop_harness import LoopHarness

CFG = default_config()
DT = CFG.sample_time_s


def _readings(fv: np.ndarray, contact: list[bool]) -> np.ndarray:
    """LVDT readings: 5 mm beyond the compression or rebound stop on contact ticks
    (alternating stops), mid-travel otherwise."""
    hi, lo = fv[F_BS_HI], fv[F_BS_LO]
    out = np.full(len(contact), 0.5 * (hi + lo))
    for k, c in enumerate(contact):
        if c:
            out[k] = hi + 0.005 if k % 2 else lo - 0.005
    return out


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=400),
       st.integers(min_value=1, max_value=40))
def test_window_is_the_exponentially_weighted_contact_time(default_runtime: BankRuntime,
                                                           pattern: list[bool],
                                                           run: int) -> None:
    """E_k = sum_i λ^(k-i) T c_i (closed form, to rounding), never above T / (1 - λ), and
    the episodes are the contact ticks that follow at least EPISODE_GAP_S without
    contact.  ``run`` stretches each drawn tick into a run of ticks (long episodes)."""
    fv, iv = fresh_buffers(default_runtime)
    contact = [c for c in pattern for _ in range(run)]
    r = _readings(fv, contact)
    sc = stop_contact_settings(CFG, DT)
    e = np.empty(len(contact))
    for k, rk in enumerate(r):
        stop_contact(fv, iv, float(rk))
        e[k] = fv[F_SC_TIME]
    c = np.asarray(contact, dtype=float)
    ticks = np.arange(c.size)
    closed = np.array([np.sum(sc.decay ** (i - ticks[: i + 1]) * DT * c[: i + 1])
                       for i in range(c.size)])
    np.testing.assert_allclose(e, closed, rtol=1e-9, atol=1e-15)
    assert np.all(e <= DT / (1.0 - sc.decay) * (1 + 1e-12))
    idx = np.flatnonzero(c)
    gap = round(EPISODE_GAP_S / DT)
    want = int(idx.size > 0) + int(np.count_nonzero(np.diff(idx) - 1 >= gap))
    assert iv[I_SC_EPISODES] == want


def test_single_episode_adds_its_duration_and_fades_with_the_window(
        default_runtime: BankRuntime) -> None:
    """From rest, d seconds of contact leave T sum λ^i ≈ τ (1 - e^(-d/τ)) <= d; after
    another τ without contact, a factor e less."""
    fv, iv = fresh_buffers(default_runtime)
    tau = CFG.safety.stop_contact_window_s
    n = round(0.2 / DT)
    for _ in range(n):
        stop_contact(fv, iv, float(fv[F_BS_HI]) + 0.01)
    e = fv[F_SC_TIME]
    assert tau * (1 - np.exp(-0.2 / tau)) == pytest.approx(e, rel=1e-3) and e <= 0.2
    for _ in range(round(tau / DT)):
        stop_contact(fv, iv, 0.0)
    assert fv[F_SC_TIME] == pytest.approx(e / np.e, rel=1e-3)


def test_degrades_above_the_budget_ramps_and_rearms(default_runtime: BankRuntime) -> None:
    """Contact beyond the budget degrades once (STOP_DEGRADED, authority ramping to
    stop_contact_authority); below the re-arm level for the re-arm time it re-arms and
    the authority ramps back to 1.  With stop_contact_degrade = false: reports only."""
    fv, iv = fresh_buffers(default_runtime)
    sa = CFG.safety
    flags = [stop_contact(fv, iv, float(fv[F_BS_HI]) + 0.01)
             for _ in range(round(2 * sa.stop_contact_budget_s / DT))]
    first = next(k for k, f in enumerate(flags) if f & StepFlag.STOP_DEGRADED)
    assert first == pytest.approx(sa.stop_contact_budget_s / DT, abs=2)
    assert iv[I_SC_NDEG] == 1 and iv[I_SC_DEG] == 1
    for _ in range(round(0.1 / DT)):
        stop_contact(fv, iv, 0.0)
    assert fv[F_SC_AUTH] == sa.stop_contact_authority
    k = 0
    while iv[I_SC_DEG]:
        stop_contact(fv, iv, 0.0)
        k += 1
    # E falls below the re-arm level after τ ln(E0 / level), then the hold time
    e0 = 2 * sa.stop_contact_budget_s
    t_rearm = 0.1 + k * DT
    want = sa.stop_contact_window_s * np.log(e0 / sa.stop_contact_rearm_level_s) \
        + sa.stop_contact_rearm_s
    assert t_rearm == pytest.approx(want, rel=0.05)
    assert iv[I_SC_NDEG] == 1
    for _ in range(round(CFG.safety.estimator_authority_ramp_s / DT) + 1):
        stop_contact(fv, iv, 0.0)
    assert fv[F_SC_AUTH] == 1.0
    off = BankRuntime(cached_design(CFG), cfg=CFG.replace(safety={"stop_contact_degrade": False}))
    fv, iv = fresh_buffers(off)
    for _ in range(round(1.0 / DT)):
        f = stop_contact(fv, iv, float(fv[F_BS_HI]) + 0.01)
        assert not f & StepFlag.STOP_DEGRADED and f & StepFlag.STOP_CONTACT
    assert fv[F_SC_AUTH] == 1.0 and fv[F_SC_TIME] > CFG.safety.stop_contact_budget_s


@pytest.mark.parametrize(("key", "value"), [("stop_contact_rearm_level_s", 0.05),
                                            ("stop_contact_band_m", 0.08)])
def test_bad_settings_name_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"safety.{key}"):
        default_config().replace(safety={key: value})


def test_loop_records_episodes_and_degradations(armed: LoopHarness) -> None:
    """The loop turns the bank's STOP_CONTACT / STOP_DEGRADED edges into notes with the
    window's contact time, counts them, keeps the valve driven (no fault) and carries
    the contact time and the flag in its tick record and status."""
    h = armed
    events = h.capture_events()
    h.rt.stop_contact_s = 0.02
    h.rt.flags = int(StepFlag.STOP_CONTACT)
    h.step()
    h.rt.flags = 0
    h.step()
    assert events[-1][1]["stop_contact"] == "episode"
    assert events[-1][1]["contact_s_in_window"] == 0.02 and events[-1][1]["episodes"] == 1
    h.rt.stop_contact_s = 0.05
    h.rt.flags = int(StepFlag.STOP_CONTACT | StepFlag.STOP_DEGRADED)
    valves, faults = h.step()
    assert valves[-1].enable == 1 and not faults
    assert ("note", {"stop_contact": "degraded", "contact_s_in_window": 0.05,
                     "stop_degradations": 1}) in events
    h.loop._tick_record(0)                           # (packs the record, as each tick does)
    scalars = h.loop._record_scalars(h.loop)
    keys = [k for k, kind, _ in TICK_RECORD_FIELDS if kind != "array"]
    rec = dict(zip(keys, scalars, strict=True))
    assert rec["stop_contact_s"] == 0.05 and rec["stop_degraded"] is True
    assert h.loop.status()["stop_degraded"]
    assert snapshot_of(0, rec, h.loop.status())["state"]["stop_degraded"] is True
    h.rt.stop_contact_s = 0.0
    h.rt.flags = 0
    h.step()
    assert events[-1] == ("note", {"stop_contact": "re-armed", "contact_s_in_window": 0.0,
                                   "stop_degradations": 1})
    assert h.loop.stop_contact_episodes == 2 and h.loop.stop_degradations == 1


def _burst_then_flat(seed: int = 6, start_s: float = 50.0, burst_s: float = 10.0,
                     flat_s: float = 6.0) -> Road:
    """The thesis course of road seed 6 from ``start_s`` (where weight set 2 rides the
    stops for most of a second), from rest, then ``flat_s`` of level road."""
    full = make_road("rough-course", 11.176, start_s + burst_s, DT, seed)
    i0 = round(start_s / DT)
    h = full.height_m[i0:] - full.height_m[i0]
    v = full.velocity_mps[i0:].copy()
    n_flat = round(flat_s / DT)
    return replace(full, name="rough-course-burst",
                   height_m=np.r_[h, np.full(n_flat, h[-1])],
                   velocity_mps=np.r_[v, np.zeros(n_flat)])


def test_degrade_reduces_contact_on_the_nonlinear_plant_and_rearms() -> None:
    """Weight set 2 on the burst of the thesis course that drives the body into the
    stops: with the monitor reporting only it stays on them for over 0.5 s and slams;
    with the degrade the monitor degrades, the contact falls to under a third with no
    slam and no fault, the absorbed power is not worse, and it re-arms on the level road
    after (no contact, the window fades).  The guard's rate lead (§9.6), which by itself
    keeps this burst under 0.1 s on the stops, the travel governor (§12) and the stop
    clamp's braking (§12: 0.245 s on the stops here with the monitor reporting only) are
    off: the monitor alone is measured."""
    road = _burst_then_flat()
    cfg = CFG.replace(design={"stop_guard_lead_s": 0.0, "govern_comfort_set": False,
                              "preview_clamp_brake": False})
    off = simulate(cfg.replace(safety={"stop_contact_degrade": False}), road, "fuzzy", 2,
                   seed=6).metrics
    ctrl = BankController(cached_design(cfg), cfg, "fuzzy", 2, road)
    on = run_closed_loop(cfg, road, ctrl, seed=6).metrics
    assert off["bump_stop_time_s"] > 0.5 and off["bump_stop_slam"] == 1.0
    assert off["stop_degradations"] == 0.0 and off["stop_contact_episodes"] >= 1
    assert on["stop_degradations"] >= 1.0 and on["n_faults"] == 0.0
    assert on["bump_stop_time_s"] < off["bump_stop_time_s"] / 3
    assert on["bump_stop_slam"] == 0.0
    assert on["absorbed_power"] <= off["absorbed_power"]
    assert not ctrl.rt.stop_degraded and ctrl.rt.stop_authority == 1.0   # re-armed
    assert ctrl.rt.stop_contact_s < CFG.safety.stop_contact_rearm_level_s
