"""The rig's sensors: LVDT (rattlespace), load cell (actuator force), accelerometer.

Signal chain per tick (all reproducible from one seed, ``numpy.random.Generator``):

* LVDT: rattlespace about the nominal static position + white noise
  (``noise.rattlespace_std_m``), quantised to ``sensors.lvdt_resolution_m``, clipped to
  +-``sensors.lvdt_range_m``.
* Load cell: actuator force + ``sensors.load_cell_offset_n`` + white noise
  (``noise.force_std_n``), clipped to +-``sensors.load_cell_range_n``.
* Accelerometer: sprung acceleration (gravity removed) + ``sensors.accel_bias_mps2``
  through a first-order low-pass of bandwidth ``sensors.accel_bandwidth_hz`` (bilinear
  transform pre-warped at the bandwidth, so the discrete filter is exactly -3 dB there),
  + white noise (``noise.accel_std_mps2``), clipped to +-``sensors.accel_range_mps2``.

A reading outside its range (or a non-finite true value) sets that sensor's bit in
``status`` (DBC ``SensorStatus``: bit0 LVDT, bit1 load cell, bit2 accelerometer); a
non-finite value reads 0.  Noise is drawn in blocks of ``BLOCK`` ticks, always in the
same order, so equal seeds give bit-identical readings.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import numpy as np

from controller.config import NoiseConfig, SensorConfig
from rig.wire.protocol import SensorStatus

__all__ = ["BLOCK", "SensorReading", "SensorStatus", "SensorSuite", "TrueSignalSource"]

BLOCK = 1024


class SensorReading(NamedTuple):
    rattlespace_m: float
    force_n: float
    accel_mps2: float
    status: int


class TrueSignalSource(Protocol):
    def true_signals(self) -> tuple[float, float, float]: ...


def _clip(value: float, limit: float) -> tuple[float, bool]:
    if not math.isfinite(value):
        return 0.0, True
    if value > limit:
        return limit, True
    if value < -limit:
        return -limit, True
    return value, False


class SensorSuite:
    """Sensor models of the rig, sampled every ``dt_s``."""

    def __init__(self, sensors: SensorConfig, noise: NoiseConfig, seed: int | None = None,
                 dt_s: float = 1e-3) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        self.sensors = sensors
        self.noise = noise
        self.seed = sensors.seed if seed is None else int(seed)
        self.dt_s = float(dt_s)
        self.std = np.array([noise.rattlespace_std_m, noise.force_std_n, noise.accel_std_mps2])
        # first-order low-pass 1 / (1 + s / wc), Tustin pre-warped at wc
        wc = 2.0 * math.pi * sensors.accel_bandwidth_hz
        nyq = math.pi / self.dt_s
        self.lp_pass = wc >= 0.999 * nyq          # bandwidth beyond Nyquist: pass through
        self.lp_b, self.lp_a = 1.0, 0.0
        if not self.lp_pass:
            k = math.tan(wc * self.dt_s / 2.0)
            self.lp_b = k / (1.0 + k)             # y = b (x + x_prev) - a y_prev
            self.lp_a = (k - 1.0) / (1.0 + k)
        self.reset()

    def reset(self) -> None:
        """Restart the noise sequence from the seed and clear the filter state."""
        self.rng = np.random.default_rng(self.seed)
        self._block = np.zeros((0, 3))
        self._i = 0
        self._lp_x = math.nan     # initialised on the first sample (no start transient)
        self._lp_y = 0.0

    def _noise(self) -> tuple[float, float, float]:
        if self._i >= self._block.shape[0]:
            self._block = self.rng.standard_normal((BLOCK, 3)) * self.std
            self._i = 0
        row = self._block[self._i]
        self._i += 1
        return float(row[0]), float(row[1]), float(row[2])

    def accel_filter(self, x: float) -> float:
        """One step of the accelerometer's low-pass (state kept between calls)."""
        if self.lp_pass or not math.isfinite(x):
            return x
        if math.isnan(self._lp_x):
            self._lp_x = self._lp_y = x
            return x
        y = self.lp_b * (x + self._lp_x) - self.lp_a * self._lp_y
        self._lp_x, self._lp_y = x, y
        return y

    def measure(self, rattlespace_m: float, force_n: float, accel_mps2: float) -> SensorReading:
        """Readings of one tick from the true signals (rattlespace about static)."""
        s = self.sensors
        n_r, n_f, n_a = self._noise()
        status = 0
        r = rattlespace_m + n_r
        if s.lvdt_resolution_m > 0.0 and math.isfinite(r):
            r = s.lvdt_resolution_m * round(r / s.lvdt_resolution_m)
        r, bad = _clip(r, s.lvdt_range_m)
        status |= SensorStatus.LVDT_FAULT if bad else 0
        f, bad = _clip(force_n + s.load_cell_offset_n + n_f, s.load_cell_range_n)
        status |= SensorStatus.LOAD_CELL_FAULT if bad else 0
        a, bad = _clip(self.accel_filter(accel_mps2 + s.accel_bias_mps2) + n_a,
                       s.accel_range_mps2)
        status |= SensorStatus.ACCEL_FAULT if bad else 0
        return SensorReading(r, f, a, int(status))

    def read(self, plant: TrueSignalSource) -> SensorReading:
        """Readings of one tick from ``plant.true_signals()``."""
        r, f, a = plant.true_signals()
        return self.measure(r, f, a)
