"""The wheel-hop frequency fit (controller/wheel_hop.py): it recovers a known oscillator,
tells the emulated rig's tires apart, honours its mask and says NaN where it cannot fit;
the runtime's tracker, and the loop's tick record and telemetry state carrying its
estimate."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest
from scipy.signal import cont2discrete, dlsim, lsim

from controller.artifact import Design
from controller.config import RigConfig, default_config
from controller.plant import (
    linear_model,
    static_tire_deflection_m,
    tire_damping_ns_per_m,
    tire_secant_stiffness_n_per_m,
)
from controller.runtime.bank import BankRuntime
from controller.wheel_hop import (
    MIN_FIT_S,
    TIRE_SCALE_RANGE,
    passive_wheel_hop_hz,
    tire_stiffness_scale,
    wheel_hop_frequency_hz,
)
from hil.sim.closed_loop import simulate
from hil.sim.roads import make_road
from rig.recording.codec import TickDecoder, iter_items
from rig.recording.schema import (
    NONFINITE_NUMBER,
    TOPIC_INTERNALS,
    TOPICS,
    encode_json,
    encode_message,
    split_record,
)
from rig.service.loop import TICK_RECORD_FIELDS
from rig.telemetry_process.child import snapshot_of
from tests.support.loop_harness import LoopHarness

DT = 1e-3


def _oscillator(f0_hz: float, zeta: float, seconds: float, seed: int) -> np.ndarray:
    """Displacement of a damped oscillator (natural frequency f0, damping ratio zeta)
    driven by white noise, sampled every DT, plus a slow body-like drift at 1.2 Hz."""
    rng = np.random.default_rng(seed)
    n = round(seconds / DT)
    t = np.arange(n) * DT
    w0 = 2.0 * math.pi * f0_hz
    _, y, _ = lsim(([1.0], [1.0, 2.0 * zeta * w0, w0 * w0]), rng.standard_normal(n), t)
    return np.asarray(y) + 5.0 * float(np.std(y)) * np.sin(2.0 * math.pi * 1.2 * t)


def test_orders_known_oscillators_within_the_documented_bias() -> None:
    """Damped frequencies fd = f0 sqrt(1 - zeta^2) of 7 / 10 / 13 Hz oscillators, with a
    body mode five times the oscillation's size riding under them (the band-pass takes it
    out): in order, each within the bias toward the band's centre that the module
    documents (+12 % at 7 Hz, -4 % at 13 Hz; bounds 15 %, 4 %, 6 %)."""
    fd = {f0: f0 * math.sqrt(0.96) for f0 in (7.0, 10.0, 13.0)}
    got = {f0: wheel_hop_frequency_hz(_oscillator(f0, 0.2, 30.0, seed=1), DT) for f0 in fd}
    assert got[7.0] < got[10.0] < got[13.0]
    assert 1.0 < got[7.0] / fd[7.0] < 1.15
    assert got[10.0] == pytest.approx(fd[10.0], rel=0.04)
    assert 0.94 < got[13.0] / fd[13.0] < 1.0


def test_the_mask_chooses_the_readings() -> None:
    """Two oscillators one after the other: each half of the mask gives its own (the one
    alone, fitted by itself, to 1 %), the whole run something between."""
    a, b = _oscillator(8.0, 0.2, 15.0, seed=2), _oscillator(12.0, 0.2, 15.0, seed=3)
    y = np.concatenate([a, b])
    first = np.arange(y.size) < a.size
    fa, fb = wheel_hop_frequency_hz(a, DT), wheel_hop_frequency_hz(b, DT)
    assert wheel_hop_frequency_hz(y, DT, first) == pytest.approx(fa, rel=0.01)
    assert wheel_hop_frequency_hz(y, DT, ~first) == pytest.approx(fb, rel=0.01)
    assert fa < wheel_hop_frequency_hz(y, DT) < fb


def test_nan_where_no_fit_is_possible() -> None:
    y = _oscillator(10.0, 0.2, 20.0, seed=4)
    assert math.isnan(wheel_hop_frequency_hz(y[:round(0.9 * MIN_FIT_S / DT)], DT))
    assert math.isnan(wheel_hop_frequency_hz(np.full(y.size, np.nan), DT))
    assert math.isnan(wheel_hop_frequency_hz(y, DT, np.zeros(y.size, dtype=bool)))
    assert math.isnan(wheel_hop_frequency_hz(y, 0.05))          # 5-20 Hz above Nyquist
    assert math.isnan(wheel_hop_frequency_hz(np.zeros(0), DT))
    whole = wheel_hop_frequency_hz(y, DT)
    y[1000:1100] = np.nan                                        # a gap is not a failure
    assert wheel_hop_frequency_hz(y, DT) == pytest.approx(whole, rel=0.01)


def test_tells_the_emulated_rigs_tires_apart_and_their_stiffness() -> None:
    """Passive on the thesis course, the measured LVDT of 10 s: a tire 0.7 / 1 / 1.3 x as
    stiff reads at least 0.4 Hz apart in order, the same tire within 0.1 Hz over two
    road seeds (measured: 8.74 / 8.77, 9.47 / 9.55, 10.14 / 10.13 Hz), and inverted
    through the prediction gives each tire's stiffness within 5 % (measured 0.720 / 0.729,
    0.993 / 1.022, 1.267 / 1.264)."""
    cfg = default_config()
    got: dict[float, list[float]] = {}
    for scale in (0.7, 1.0, 1.3):
        plant = dataclasses.replace(cfg, emulator=dataclasses.replace(
            cfg.emulator, tire_stiffness_scale=scale))
        for seed in (1, 2):
            road = make_road("rough-course", 11.176, 12.0, cfg.sample_time_s, seed)
            y = simulate(plant, road, "passive", 1, seed=seed).traces["meas_rattlespace_m"]
            got.setdefault(scale, []).append(
                wheel_hop_frequency_hz(y[round(2.0 / cfg.sample_time_s):], cfg.sample_time_s))
    for scale, fs in got.items():
        assert max(fs) - min(fs) < 0.1, (scale, fs)
        for f in fs:
            assert tire_stiffness_scale(f, cfg) == pytest.approx(scale, rel=0.05), (scale, f)
    assert min(got[1.0]) - max(got[0.7]) > 0.4, got
    assert min(got[1.3]) - max(got[1.0]) > 0.4, got


def _linear_passive_lvdt(cfg: RigConfig, seconds: float, seed: int) -> np.ndarray:
    """Rattlespace of the linear quarter car of ``cfg`` (tangent tire stiffness at the
    static deflection) driven by white road velocity, simulated tick by tick."""
    x2 = static_tire_deflection_m(cfg)
    lm = linear_model(cfg.vehicle,
                      tire_secant_stiffness_n_per_m(x2, cfg.tire) * cfg.tire.stiffness_exponent,
                      tire_damping_ns_per_m(x2, cfg.tire))
    n = round(seconds / DT)
    w = np.random.default_rng(seed).standard_normal(n)
    _, y, _ = dlsim(cont2discrete((lm.A, lm.B1[:, None], lm.C_meas[:1], np.zeros((1, 1))),
                                  DT), w)
    return np.asarray(y)[:, 0]


@pytest.mark.parametrize("scale", [0.7, 1.0, 1.3])
def test_prediction_is_the_fit_on_a_simulated_linear_rig(scale: float) -> None:
    """The Lyapunov / Yule-Walker prediction against the mean of the fit itself on six
    runs of 120 s of the same linear rig simulated tick by tick: within 0.05 Hz
    (measured +0.003 to +0.026 Hz; one run's fit spreads over about 0.2 Hz)."""
    cfg = default_config()
    cfg = cfg.replace(tire={"stiffness_coefficient": cfg.tire.stiffness_coefficient * scale})
    fitted = [wheel_hop_frequency_hz(_linear_passive_lvdt(cfg, 120.0, seed), DT)
              for seed in range(6)]
    assert passive_wheel_hop_hz(cfg) == pytest.approx(float(np.mean(fitted)), abs=0.05)


def test_tire_scale_inverts_the_prediction_and_says_nan_outside_it() -> None:
    cfg = default_config()
    for scale in (0.5, 0.8, 1.0, 1.6):
        f = passive_wheel_hop_hz(cfg.replace(tire={
            "stiffness_coefficient": cfg.tire.stiffness_coefficient * scale}))
        assert tire_stiffness_scale(f, cfg) == pytest.approx(scale, rel=1e-3)
    f_lo = passive_wheel_hop_hz(cfg.replace(tire={
        "stiffness_coefficient": cfg.tire.stiffness_coefficient * TIRE_SCALE_RANGE[0]}))
    assert math.isnan(tire_stiffness_scale(0.9 * f_lo, cfg))
    assert math.isnan(tire_stiffness_scale(math.nan, cfg))
    assert math.isnan(passive_wheel_hop_hz(cfg, dt_s=0.05))     # band above Nyquist
    # the rest of the rig moves the wheel hop too: more damping reads as a softer tire
    damped = cfg.replace(vehicle={"suspension_damping_ns_per_m":
                                  1.5 * cfg.vehicle.suspension_damping_ns_per_m})
    assert passive_wheel_hop_hz(damped) < passive_wheel_hop_hz(cfg)
    assert tire_stiffness_scale(passive_wheel_hop_hz(damped), cfg) < 0.9


def _passive_readings(tire_scale: float, seconds: float, seed: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(LVDT [m], accelerometer [m/s^2], load cell [N]) of a passive run of the emulated
    rig with a tire ``tire_scale`` x as stiff on the thesis course."""
    cfg = default_config()
    plant = cfg.replace(emulator={"tire_stiffness_scale": tire_scale})
    road = make_road("rough-course", 11.176, seconds, cfg.sample_time_s, seed)
    tr = simulate(plant, road, "passive", 1, seed=seed).traces
    return tr["meas_rattlespace_m"], tr["meas_accel_mps2"], tr["meas_force_n"]


def _run(rt: BankRuntime, r: np.ndarray, a: np.ndarray, f: np.ndarray) -> None:
    for k in range(r.size):
        rt.step(float(r[k]), float(a[k]), float(f[k]))


def test_runtime_tracker_is_the_fit_of_the_passive_stretch(default_design: Design) -> None:
    """The bank's tracker on 16 s of a passive run (a 0.7 x tire): nothing before 8 s
    of data, then the frequency of the offline fit over the same readings within
    0.1 Hz (measured 0.03 Hz; the tracker weighs old samples less), the stiffness the
    prediction gives for it within 1 % (a table against a root search), about 0.7."""
    cfg = default_config()
    r, a, f = _passive_readings(0.7, 16.0, seed=1)
    rt = BankRuntime(default_design, cfg=cfg)
    rt.reset()
    _run(rt, r[:8000], a[:8000], f[:8000])
    assert math.isnan(rt.wheel_hop_hz) and math.isnan(rt.tire_stiffness_est)
    _run(rt, r[8000:], a[8000:], f[8000:])
    assert rt.counters()["wheel_hop_updates"] > 0
    assert rt.wheel_hop_hz == pytest.approx(wheel_hop_frequency_hz(r[500:], DT), abs=0.1)
    assert rt.tire_stiffness_est == pytest.approx(
        tire_stiffness_scale(rt.wheel_hop_hz, cfg), rel=0.01)
    assert rt.tire_stiffness_est == pytest.approx(0.7, rel=0.06)


def test_runtime_tracker_holds_while_the_load_cell_reads_force_and_on_a_quiet_rig(
        default_design: Design) -> None:
    """Armed (the load cell reads the actuator's force) the estimate holds, whatever the
    LVDT does; a rig at rest (LVDT noise alone) gives no estimate: the fit of noise
    would be the band's centre; a reset forgets the estimate."""
    cfg = default_config()
    r, a, f = _passive_readings(1.0, 12.0, seed=2)
    rt = BankRuntime(default_design, cfg=cfg)
    rt.reset()
    _run(rt, r, a, f)
    held, n = rt.wheel_hop_hz, rt.counters()["wheel_hop_updates"]
    assert math.isfinite(held)
    t = np.arange(r.size) * DT
    _run(rt, r[::-1].copy(), a, 1500.0 * np.sin(2.0 * np.pi * 3.0 * t) + 800.0)
    assert rt.wheel_hop_hz == held and rt.counters()["wheel_hop_updates"] == n
    rt.reset()
    assert math.isnan(rt.wheel_hop_hz)
    noise = cfg.noise.rattlespace_std_m * np.random.default_rng(3).standard_normal(15000)
    _run(rt, noise, np.zeros(noise.size), np.zeros(noise.size))
    assert math.isnan(rt.wheel_hop_hz) and rt.counters()["wheel_hop_updates"] == 0


def test_the_loop_records_and_publishes_the_tire_estimate(armed: LoopHarness) -> None:
    """The tick record carries the bank's wheel hop and tire stiffness right after the
    damping estimate, as they were on that tick: through the packed record (recording
    and telemetry) into the recording's /controller/internals message and the Zenoh
    state; not yet estimated (NaN) they are the non-finite marker there and null in the
    state, their keys listed in ``nonfinite``."""
    h = armed
    keys = [k for k, _kind, _src in TICK_RECORD_FIELDS]
    i = keys.index("damping_est_ns_per_m")
    assert keys[i + 1:i + 3] == ["wheel_hop_hz", "tire_stiffness_est"]
    for key, unit in (("wheel_hop_hz", "[Hz]"), ("tire_stiffness_est", "[x configured]")):
        prop = TOPICS[TOPIC_INTERNALS]["properties"][key]
        assert prop["type"] == "number" and unit in prop["description"], key

    def published(hop: float, scale: float) -> tuple[dict[str, Any], dict[str, Any],
                                                     dict[str, Any]]:
        h.rt.wheel_hop_hz, h.rt.tire_stiffness_est = hop, scale
        h.step()
        packed = bytes(h.loop._tick_record(0))
        _t, rec = TickDecoder(h.loop._packer.layout).decode(next(iter_items(packed)))
        parts = dict(split_record(0, rec))
        internals = json.loads(encode_message(parts[TOPIC_INTERNALS]))
        state = json.loads(encode_json(snapshot_of(0, rec, h.loop.status())["state"]))
        return rec, internals, state

    rec, internals, state = published(9.31, 0.93)
    for key, v in (("wheel_hop_hz", 9.31), ("tire_stiffness_est", 0.93)):
        assert rec[key] == internals[key] == state[key] == v, key
    assert "nonfinite" not in internals and "nonfinite" not in state
    rec, internals, state = published(math.nan, math.nan)
    for key in ("wheel_hop_hz", "tire_stiffness_est"):
        assert math.isnan(rec[key]), key
        assert internals[key] == NONFINITE_NUMBER and key in internals["nonfinite"], key
        assert state[key] is None and key in state["nonfinite"], key
    assert rec["damping_est_ns_per_m"] == internals["damping_est_ns_per_m"] == 1650.0
