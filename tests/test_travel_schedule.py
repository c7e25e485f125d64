"""Travel schedule (controller/travel_schedule.py, docs/design.md §12): the numba kernel
against the plain-Python law, the blend's end points against the two weight sets it
blends, the configuration's checks, and a course run on the nonlinear rig."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import ConfigError, default_config
from controller.runtime.bank import BankRuntime
from controller.runtime.kernels import (
    F_TS,
    F_TS_BETA,
    F_TS_ENV,
    F_TS_ON,
    FV_HEAD,
    travel_comfort_share,
)
from controller.travel_schedule import SCHEDULE_SIZE, THRESHOLDS, comfort_share, travel_schedule
from hil.sim.closed_loop import cached_design, simulate
from hil.sim.roads import make_road
from rig.service.loop import TICK_RECORD_FIELDS
from rig.telemetry_process.child import snapshot_of
from tests.support.loop_harness import LoopHarness


def _python_law(readings: list[float]) -> list[float]:
    """The schedule of the default configuration in plain Python: peak-hold envelope of
    the distance from the stops' centre, then the smoothstep share."""
    sch = travel_schedule(default_config())
    env, out = 0.0, []
    for r in readings:
        env = max(abs(r - sch.centre_m), env * sch.release_decay)
        out.append(comfort_share(env, sch))
    return out


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-0.12, 0.12, allow_nan=False), min_size=1, max_size=200))
def test_kernel_is_the_plain_law(readings: list[float]) -> None:
    fv = np.zeros(FV_HEAD)
    fv[F_TS_ON] = 1.0
    fv[F_TS:F_TS + SCHEDULE_SIZE] = travel_schedule(default_config()).as_array()
    got = [travel_comfort_share(fv, r) for r in readings]
    assert got == pytest.approx(_python_law(readings), abs=1e-12)
    assert all(0.0 <= b <= 1.0 for b in got)
    assert fv[F_TS_BETA] == got[-1]


def test_thresholds_by_name() -> None:
    d = default_config().design
    want = {"reading": (d.schedule_start_m, d.schedule_full_m),
            "preview": (d.preview_schedule_start_m, d.preview_schedule_full_m),
            "governor": (d.governor_start_m, d.governor_full_m)}
    assert set(THRESHOLDS) == set(want)
    for name, (start, full) in want.items():
        sch = travel_schedule(default_config(), name)
        assert (sch.start_m, sch.full_m) == (start, full)
    assert travel_schedule(default_config()) == travel_schedule(default_config(), "reading")
    with pytest.raises(ValueError, match="schedule thresholds 'live'"):
        travel_schedule(default_config(), "live")  # type: ignore[arg-type]


def test_share_is_monotone_and_spans_the_band() -> None:
    sch = travel_schedule(default_config())
    usage = np.linspace(0.0, 0.1, 401)
    beta = [comfort_share(float(e), sch) for e in usage]
    assert beta[0] == 1.0 and beta[-1] == 0.0
    assert all(b1 <= b0 for b0, b1 in itertools.pairwise(beta))
    assert comfort_share(sch.start_m, sch) == 1.0 and comfort_share(sch.full_m, sch) == 0.0


def test_off_is_zero_and_a_nonfinite_reading_only_decays_the_envelope() -> None:
    fv = np.zeros(FV_HEAD)
    fv[F_TS:F_TS + SCHEDULE_SIZE] = travel_schedule(default_config()).as_array()
    assert travel_comfort_share(fv, 0.0) == 0.0          # F_TS_ON = 0: schedule off
    fv[F_TS_ON] = 1.0
    travel_comfort_share(fv, 0.05)
    env = fv[F_TS_ENV]
    beta = travel_comfort_share(fv, math.nan)       # (bank_step refuses such a reading first)
    assert 0.0 < fv[F_TS_ENV] <= env and 0.0 <= beta <= 1.0


def _forces(weight_set: int, readings: np.ndarray, **design: object) -> np.ndarray:
    cfg = default_config().replace(design=design) if design else default_config()
    rt = BankRuntime(cached_design(cfg), weight_set=weight_set, cfg=cfg)
    return np.array([rt.step(r, a, f) for r, a, f in readings])


ALONE = {"govern_comfort_set": False}      # the comfort set alone, not governed


def test_blend_end_points_are_the_two_weight_sets() -> None:
    """Fed the same sensor readings (the filters take the measured force as their input,
    so the estimates are the same), the scheduled bank gives weight set 2's force while
    the rattlespace stays inside schedule_start_m, and weight set 1's once the envelope
    is beyond schedule_full_m."""
    cfg = default_config()
    comfort, travel = cfg.design.schedule_weight_sets
    rng = np.random.default_rng(3)
    n = 400
    small = np.column_stack([0.01 * np.sin(np.arange(n) * 0.05), rng.normal(0, 0.5, n),
                             rng.normal(0, 50.0, n)])
    np.testing.assert_allclose(_forces(0, small), _forces(comfort, small, **ALONE),
                               rtol=1e-9, atol=1e-9)
    big = small.copy()
    big[:, 0] += 0.07            # well beyond schedule_full_m from the stops' centre
    np.testing.assert_allclose(_forces(0, big), _forces(travel, big), rtol=1e-9, atol=1e-9)
    assert not np.allclose(_forces(comfort, big, **ALONE), _forces(travel, big))


def test_governed_comfort_set_is_untouched_until_near_the_stops() -> None:
    """The comfort set selected alone runs under the travel governor: its own force while
    the reading stays inside design.governor_start_m, the travel set's beyond
    governor_full_m; the travel set and, with govern_comfort_set false, the comfort set
    run alone."""
    cfg = default_config()
    comfort, travel = cfg.design.schedule_weight_sets
    rng = np.random.default_rng(4)
    n = 400
    c = cfg.design.bump_stop_centre_lvdt_m
    small = np.column_stack([c + 0.05 * np.sin(np.arange(n) * 0.05), rng.normal(0, 0.5, n),
                             rng.normal(0, 50.0, n)])
    assert cfg.design.schedule_start_m < 0.05 < cfg.design.governor_start_m
    alone = _forces(comfort, small, **ALONE)
    np.testing.assert_allclose(_forces(comfort, small), alone, rtol=1e-9, atol=1e-9)
    assert not np.allclose(_forces(0, small), alone)     # the schedule has turned already
    far = small.copy()
    far[:, 0] = c + 0.005 * np.sin(np.arange(n) * 0.05) + cfg.design.governor_full_m + 0.006
    np.testing.assert_allclose(_forces(comfort, far), _forces(travel, far), rtol=1e-9,
                               atol=1e-9)
    design = cached_design(cfg)
    gov = BankRuntime(design, weight_set=comfort, cfg=cfg)
    assert gov.governed and gov._fv[F_TS_ON] == 1.0
    for live in (False, True):      # the governor's thresholds, preview live or not
        gov.use_preview_schedule(live)
        np.testing.assert_array_equal(gov._fv[F_TS:F_TS + SCHEDULE_SIZE],
                                      travel_schedule(cfg, "governor").as_array())
    assert not BankRuntime(design, weight_set=travel, cfg=cfg).governed
    off = default_config().replace(design=ALONE)
    rt = BankRuntime(cached_design(off), weight_set=comfort, cfg=off)
    assert not rt.governed and rt._fv[F_TS_ON] == 0.0
    rt.set_weight_set(0)            # the operator selects the schedule: not governed
    assert not rt.governed and rt._fv[F_TS_ON] == 1.0
    # a travel set the design does not have: no governor, and the service's start-up
    # message (DesignConfig.governs) says the same as the runtime
    stray = default_config().replace(design={"schedule_weight_sets": [2, 3], "weight_set": 2})
    assert not stray.design.governs(2)
    assert not BankRuntime(design, weight_set=2, cfg=stray).governed


def test_configuration_checks_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"design\.schedule_weight_sets"):
        default_config().replace(design={"weight_set": 0, "schedule_weight_sets": [3, 1]})
    with pytest.raises(ConfigError, match=r"design\.schedule_full_m"):
        default_config().replace(design={"schedule_start_m": 0.05, "schedule_full_m": 0.04})
    with pytest.raises(ConfigError, match=r"design\.governor_full_m"):
        default_config().replace(design={"governor_start_m": 0.08, "governor_full_m": 0.07})
    one = default_config().replace(design={"weight_set": 1, "weight_sets": [[1.0, 1e2, 1e-8, 1.0]]})
    rt = BankRuntime(cached_design(one), weight_set=1, cfg=one)
    with pytest.raises(ValueError, match="travel schedule"):
        rt.set_weight_set(0)


@pytest.mark.parametrize("seed", [10])
def test_course_run_keeps_off_the_stops_with_more_comfort_than_set_1(seed: int) -> None:
    """Thesis course, a road seed on which weight set 2 slams the stops and passive does
    not: the schedule does not slam, spends at most passive's time + 0.1 % of the run on
    the stops, and absorbs less power than weight set 1.  The guard's rate lead (§9.6)
    and the road preview's stop clamp (§12), each of which keeps weight set 2 off the
    stops on this seed too, are off: the schedule alone is measured."""
    cfg = default_config().replace(design={"stop_guard_lead_s": 0.0,
                                           "preview_stop_clamp_m": 0.0})
    road = make_road("rough-course", 11.176, 60.0, cfg.sample_time_s, seed)
    res = {w: simulate(cfg, road, "fuzzy", w, seed=seed).metrics for w in (0, 1, 2)}
    alone = simulate(cfg.replace(design=ALONE), road, "fuzzy", 2, seed=seed).metrics
    passive = simulate(cfg, road, "passive", 1, seed=seed).metrics
    assert alone["bump_stop_slam"] and not passive["bump_stop_slam"]   # the case it is for
    for law in (res[0], res[2]):    # the schedule, and weight set 2 under the governor
        assert not law["bump_stop_slam"] and law["n_faults"] == 0
        assert law["bump_stop_time_s"] <= passive["bump_stop_time_s"] + 0.001 * 60.0
        assert law["absorbed_power"] < 0.8 * res[1]["absorbed_power"]
        assert 0.0 < law["schedule_comfort_share"] < 1.0
    assert res[2]["preview_call_fraction"] > 0.0 and alone["preview_call_fraction"] == 0.0


def test_loop_records_and_publishes_the_comfort_share(armed: LoopHarness) -> None:
    """The tick record carries the bank's comfort share as it was on that tick, and the
    telemetry state built from the record shows it."""
    h = armed
    h.rt.comfort_share = 0.25
    h.step()
    h.loop._tick_record(0)
    keys = [k for k, kind, _ in TICK_RECORD_FIELDS if kind != "array"]
    rec = dict(zip(keys, h.loop._record_scalars(h.loop), strict=True))
    assert rec["comfort_share"] == 0.25
    assert snapshot_of(0, rec, h.loop.status())["state"]["comfort_share"] == 0.25
