"""Sensor models of the emulated rig (hil/sim/sensors.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from hil.sim.plant import RigPlant
from hil.sim.sensors import SensorStatus, SensorSuite

CFG = default_config()
DT = 1e-3


def _suite(sensors: dict | None = None, noise: dict | None = None, seed: int = 1):
    cfg = CFG.replace(sensors=sensors or {}, noise=noise or {})
    return SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=DT)


def _readings(suite: SensorSuite, r, f, a) -> np.ndarray:
    return np.array([suite.measure(float(x), float(y), float(z))[:3]
                     for x, y, z in zip(r, f, a, strict=True)])


def test_noise_std_and_offsets() -> None:
    s = _suite({"lvdt_resolution_m": 0.0, "load_cell_offset_n": 12.0, "accel_bias_mps2": 0.3,
                "accel_bandwidth_hz": 1e4})
    n = 20000
    z = np.zeros(n)
    out = _readings(s, z, z, z)
    assert out[:, 0].std() == pytest.approx(CFG.noise.rattlespace_std_m, rel=0.03)
    assert out[:, 1].std() == pytest.approx(CFG.noise.force_std_n, rel=0.03)
    assert out[:, 2].std() == pytest.approx(CFG.noise.accel_std_mps2, rel=0.03)
    assert out[:, 1].mean() == pytest.approx(12.0, abs=0.15)
    assert out[:, 2].mean() == pytest.approx(0.3, abs=0.003)
    assert abs(out[:, 0].mean()) < 3 * CFG.noise.rattlespace_std_m / math.sqrt(n)


@settings(max_examples=30, deadline=None)
@given(r=st.floats(-0.09, 0.09))
def test_lvdt_quantisation_step(r: float) -> None:
    res = 5e-6
    s = _suite({"lvdt_resolution_m": res}, {"rattlespace_std_m": 1e-15})
    reading = s.measure(r, 0.0, 0.0).rattlespace_m
    assert abs(reading - r) <= res / 2 + 1e-15
    assert reading / res == pytest.approx(round(reading / res), abs=1e-6)


def test_accelerometer_bandwidth_is_the_minus_3db_point() -> None:
    fc = CFG.sensors.accel_bandwidth_hz

    def gain(f_hz: float) -> float:
        s = _suite(noise={"accel_std_mps2": 1e-12})
        t = np.arange(4000) * DT
        x = np.sin(2 * math.pi * f_hz * t)
        y = _readings(s, np.zeros_like(t), np.zeros_like(t), x)[:, 2]
        tail = slice(2000, None)   # settled; fit amplitude by least squares
        basis = np.column_stack([np.sin(2 * math.pi * f_hz * t[tail]),
                                 np.cos(2 * math.pi * f_hz * t[tail])])
        coef, *_ = np.linalg.lstsq(basis, y[tail], rcond=None)
        return float(np.hypot(*coef))

    assert gain(fc) == pytest.approx(1 / math.sqrt(2), rel=0.01)
    f_low = fc / 10
    assert gain(f_low) == pytest.approx(1 / math.sqrt(1 + (f_low / fc) ** 2), rel=0.01)
    assert gain(fc / 2) > gain(fc) > gain(fc * 1.5)
    # DC gain 1 (a constant passes unchanged, no start transient)
    s = _suite(noise={"accel_std_mps2": 1e-12})
    assert _readings(s, [0] * 50, [0] * 50, [2.0] * 50)[-1, 2] == pytest.approx(2.0)


@pytest.mark.parametrize(("idx", "bit", "value", "limit"), [
    (0, SensorStatus.LVDT_FAULT, 0.5, CFG.sensors.lvdt_range_m),
    (1, SensorStatus.LOAD_CELL_FAULT, -1e5, CFG.sensors.load_cell_range_n),
    (2, SensorStatus.ACCEL_FAULT, 1e4, CFG.sensors.accel_range_mps2),
])
def test_clipping_sets_status(idx: int, bit: SensorStatus, value: float, limit: float) -> None:
    s = _suite(sensors={"accel_bandwidth_hz": 1e5})
    args = [0.0, 0.0, 0.0]
    args[idx] = value
    reading = s.measure(*args)
    assert abs(reading[idx]) == pytest.approx(limit)
    assert reading.status == int(bit)
    args[idx] = math.nan
    reading = s.measure(*args)
    assert reading[idx] == 0.0 and reading.status & int(bit)
    assert s.measure(0.0, 0.0, 0.0).status == 0


def test_same_seed_bit_identical_and_reset_restarts() -> None:
    plant = RigPlant(CFG)

    def run(seed: int) -> bytes:
        s = SensorSuite(CFG.sensors, CFG.noise, seed, dt_s=DT)
        return np.array([s.read(plant)[:3] for _ in range(3000)]).tobytes()

    assert run(5) == run(5)
    assert run(5) != run(6)
    s = SensorSuite(CFG.sensors, CFG.noise, 9, dt_s=DT)
    first = [s.read(plant) for _ in range(10)]
    s.reset()
    assert [s.read(plant) for _ in range(10)] == first
    assert SensorSuite(CFG.sensors, CFG.noise).seed == CFG.sensors.seed
