"""The identification excitation: a force reference played by the control loop.

With the road (shaker) at rest the loop's force loop tracks

    F(t) = w(t) [ A_c(f(t)) sin(phi(t)) + A_p b(t) ]                       [N]

* a logarithmic chirp from ``chirp_start_hz`` f0 to ``chirp_stop_hz`` f1 over the
  duration T: f(t) = f0 (f1/f0)^(t/T), phi(t) = 2 pi f0 T (e^(t ln(f1/f0)/T) - 1) / ln(f1/f0);
  its amplitude A_c(f) = ``chirp_amplitude_n`` x min(1, f / ``chirp_corner_hz``) so the body
  mode (~1 Hz) is not driven into the bump stops;
* a maximum-length PRBS b(t) = +/-1 (``scipy.signal.max_len_seq``, register length from the
  number of bits, start state from ``excitation.seed``) clocked at ``prbs_clock_hz``: a flat
  spectrum up to ~0.45 x the clock, for the wheel mode and the force loop;
* a cosine fade w(t) over ``taper_s`` at both ends (the run starts and ends at 0 N).

Everything comes from ``cfg.excitation`` and the seed: equal configurations give the same
samples, bit for bit.  Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from controller.config import RigConfig, excitation_problems

__all__ = ["chirp_frequency_hz", "excitation_force"]

FloatArray = NDArray[np.float64]


def chirp_frequency_hz(cfg: RigConfig, t_s: FloatArray) -> FloatArray:
    """Instantaneous chirp frequency [Hz] at times ``t_s`` since the excitation start."""
    ex = cfg.excitation
    rate = math.log(ex.chirp_stop_hz / ex.chirp_start_hz) / ex.duration_s
    return np.asarray(ex.chirp_start_hz * np.exp(rate * np.asarray(t_s)), dtype=np.float64)


def _prbs(n_bits: int, seed: int) -> FloatArray:
    """+/-1 maximum-length sequence of at least ``n_bits`` bits (seeded start state)."""
    nbits = max(4, min(24, math.ceil(math.log2(n_bits + 1))))
    rng = np.random.default_rng(seed)
    state = rng.integers(0, 2, nbits).astype(np.int8)
    if not state.any():
        state[0] = 1
    seq, _ = signal.max_len_seq(nbits, state=state, length=n_bits)
    return np.where(seq > 0, 1.0, -1.0)


def excitation_force(cfg: RigConfig) -> FloatArray:
    """The excitation's force reference [N], one sample per controller tick
    (``cfg.excitation.duration_s`` x ``cfg.design.sample_rate_hz`` samples).
    :class:`controller.config.ConfigError` when the section does not fit the rest of the
    configuration (:func:`controller.config.excitation_problems`)."""
    excitation_problems(cfg)
    ex = cfg.excitation
    dt = cfg.sample_time_s
    n = round(ex.duration_s / dt)
    t = np.arange(n, dtype=np.float64) * dt
    rate = math.log(ex.chirp_stop_hz / ex.chirp_start_hz) / ex.duration_s
    phase = 2.0 * math.pi * ex.chirp_start_hz * (np.exp(rate * t) - 1.0) / rate
    f = ex.chirp_start_hz * np.exp(rate * t)
    amp = ex.chirp_amplitude_n * (np.minimum(1.0, f / ex.chirp_corner_hz)
                                  if ex.chirp_corner_hz > 0 else np.ones(n))
    chirp = amp * np.sin(phase)
    n_bits = math.ceil(n * dt * ex.prbs_clock_hz) + 1
    bits = _prbs(n_bits, ex.seed)
    prbs = ex.prbs_amplitude_n * bits[np.minimum((t * ex.prbs_clock_hz).astype(np.int64),
                                                 n_bits - 1)]
    w = np.ones(n)
    m = round(ex.taper_s / dt)
    if m > 0:
        ramp = 0.5 - 0.5 * np.cos(math.pi * np.arange(m) / m)
        w[:m] = ramp
        w[n - m:] = ramp[::-1]
    out: FloatArray = w * (chirp + prbs)
    return out
