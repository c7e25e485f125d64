"""The wheel-hop frequency fit (controller/wheel_hop.py): it recovers a known oscillator,
tells the emulated rig's tires apart, honours its mask and says NaN where it cannot fit."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.signal import lsim

from controller.config import default_config
from controller.wheel_hop import MIN_FIT_S, wheel_hop_frequency_hz
from hil.sim.closed_loop import simulate
from hil.sim.roads import make_road

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


def test_tells_the_emulated_rigs_tires_apart() -> None:
    """Passive on the thesis course, the measured LVDT of 10 s: a tire 0.7 / 1 / 1.3 x as
    stiff reads at least 0.4 Hz apart in order, the same tire within 0.1 Hz over two
    road seeds (measured: 8.74 / 8.77, 9.47 / 9.55, 10.14 / 10.13 Hz)."""
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
    assert min(got[1.0]) - max(got[0.7]) > 0.4, got
    assert min(got[1.3]) - max(got[1.0]) > 0.4, got
