"""Identify the rig's quarter car, tire law, sensor offsets and actuator from an
identification run (``rig run --excite``; docs/identify.md).  Pure math, no I/O.

Input (:class:`RunData`): the recorded LVDT reading r, load cell F, accelerometer a, the
spool command and the force reference, the ticks of the excitation (road at rest, valve
in closed force loop) and of the passive rest before it.

Sensor offsets and noise.  During the rest the rig sits still: the mean load cell reading
is its offset (the bypass is open, the actuator force 0), the mean accelerometer reading
its bias, the standard deviations the sensors' white noise levels.

Equation error, time domain.  With the road at rest (w = 0), zs'' = a, r = zu - zs:

    body    M a = K r + C r' + F                                   (exact: linear spring)
    total   -M a = m (a + r'') + k_t (zs + r) + c_t (zs' + r') - k_2 (zs + r)^2

(the tire force about its static load L = (M + m) g expanded to second order in the tire
deflection x2 - x2s = -(zs + r); zs from a integrated twice).  Every signal goes through
one chain of linear filters, so each equation holds exactly for the filtered signals:
the accelerometer's own low-pass (``sensors.accel_bandwidth_hz``, applied to r and F, a
has it), a 4th-order Butterworth low-pass at :data:`LOWPASS_HZ` and a 2nd-order high-pass at
:data:`HIGHPASS_HZ` (offsets and drift out; divided by s^2 it integrates a), the derivatives
s^k taken inside the chain; every continuous filter is mapped to discrete time by one
bilinear transform (a ring homomorphism: products of filters stay products).
Least squares on the filtered signals with *bias compensation*: the noise of the
regressors (white, its level measured in the rest, propagated through the filters'
impulse responses) is subtracted from the normal equations.

Intervals: delete-one-block jackknife over :data:`N_BLOCKS` contiguous blocks of the
excitation (each replicate repeats the whole chain, so the body fit's uncertainty
propagates into the wheel fit, the exponent and the tire coefficient), Student t with
B - 1 degrees of freedom, widened by the ratio of the residual's correlation time to the
block length (blocks overlap through the filters' memory) and by the remaining
noise-induced bias (the size of the bias correction's own uncertainty).

Tire law f = k' (1000 x2)^e: k_t = e L / x2s and k_2 = (e - 1) k_t / (2 x2s) give
e = 1 / (1 - 2 L k_2 / k_t^2) and k' = L / (1000 x2s)^e.  When the excitation's tire
deflection is too small against x2s to resolve e (its interval wider than
:data:`EXPONENT_HALF_WIDTH`), e is *not identified* and k' is given for the configured e.

Actuator: F' = -beta F + k_h r' + gamma A x_s sqrt(Ps - sgn(x_s) F / A), x_s = stroke x_v,
x_v the spool command delayed d ticks through a first-order lag tau (the spool time
constant): linear least squares in (beta, k_h, gamma) on the same kind of filter chain
(low-pass :data:`ACTUATOR_LOWPASS_HZ`), tau by the smallest residual over a grid, d in
0..2.  k_h = alpha A^2 is the effective hydraulic stiffness.  Parameters whose interval
is wider than :data:`RELATIVE_HALF_WIDTH` of the estimate are reported not identified.

Frequency domain cross-check: Welch cross-spectra against the excitation (the force
reference, free of sensor noise) give the measured responses from the actuator force to
a and r; M, K, C fitted to them by complex least squares must agree with the time domain
(``fit.frequency_domain``); the report plots them against the model's responses.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal, stats

from controller.config import RigConfig

__all__ = ["ACTUATOR_LOWPASS_HZ", "EXPONENT_HALF_WIDTH", "HIGHPASS_HZ", "LOWPASS_HZ",
           "MIN_EXCITATION_S", "MIN_REST_S", "N_BLOCKS", "RELATIVE_HALF_WIDTH",
           "SEGMENT_SETTLE_S",
           "Identification", "IdentificationRefusedError", "RunData", "fitted_config",
           "identify", "model_frequency_response"]

FloatArray = NDArray[np.float64]

LOWPASS_HZ = 40.0           # mechanical fits: above the 25 Hz excitation
HIGHPASS_HZ = 0.15          # below the 0.5 Hz chirp start
ACTUATOR_LOWPASS_HZ = 150.0
WHEEL_LOWPASS_HZ = 30.0     # wheel / tire fit: r'' noise grows as the band's 2.5th power
WHEEL_HIGHPASS_HZ = 1.0     # ... and zs (a integrated twice) noise below ~1 Hz
N_BLOCKS = 20
MIN_EXCITATION_S = 5.0
MIN_REST_S = 0.5
EXPONENT_HALF_WIDTH = 0.05
#: the exponent is resolved only when the tire deflection's RMS is at least this fraction
#: of the static deflection (its second-order term is then >= ~5 % of the tire force
#: about static, above the tire damping's own nonlinearity that the fit leaves out)
MIN_RELATIVE_DEFLECTION = 0.15
#: the actuator's analysis bands: the spread of the estimates over them is added to the
#: interval (closed-loop and discretisation effects depend on the band)
ACTUATOR_BANDS_HZ = (40.0, 80.0, 150.0)
#: the second pair of bands of the mechanical fit (see :func:`identify`)
ALT_LOWPASS_HZ = 30.0
ALT_HIGHPASS_HZ = 0.3
ALT_WHEEL_LOWPASS_HZ = 25.0
ALT_WHEEL_HIGHPASS_HZ = 1.5
#: window of the HAC (Newey-West) standard errors [s]
HAC_LAG_S = 1.0
RELATIVE_HALF_WIDTH = 0.25
SATURATED_FRACTION = 0.005   # of the excitation's ticks
MIN_TIRE_LOAD_FRACTION = 0.02
#: after a missed / held sensor sample the filter chains restart; the ticks this long
#: after the restart (the chains settling) are left out of the fit [s]
SEGMENT_SETTLE_S = 1.0


class IdentificationRefusedError(ValueError):
    """The run cannot be identified (one-line reason)."""


@dataclass(frozen=True)
class RunData:
    """Recorded channels (one value per controller tick) and the two segments."""

    dt_s: float
    rattlespace_m: FloatArray
    accel_mps2: FloatArray
    force_n: FloatArray
    force_ref_n: FloatArray
    spool_cmd: FloatArray
    excite: NDArray[np.bool_]     # excitation playing, valve driven
    rest: NDArray[np.bool_]       # passive rest before the excitation
    #: False where the tick did not get the next sensor sample (a frame missed or held:
    #: the series is not uniformly sampled there); None = all good
    fresh: NDArray[np.bool_] | None = None


@dataclass
class Identification:
    estimates: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    not_identified: dict[str, str]
    fit: dict[str, Any]
    #: for the report: frequency responses and time traces
    curves: dict[str, FloatArray] = field(default_factory=dict)


# ---------------------------------------------------------------------------- filters


def _chain_sos(order_s: int, fc_hz: float, hp_hz: float, fs: float,
               lp_order: int = 4) -> NDArray[np.float64]:
    """sos of s^order_s x Butterworth low-pass x H(s) / s^2, H the 2nd-order Butterworth
    high-pass (so order_s = 2 is the band-pass, 0 integrates twice), by the bilinear map."""
    _, p_lp, k_lp = signal.butter(lp_order, 2 * math.pi * fc_hz, analog=True,
                                     output="zpk")
    w0 = 2 * math.pi * hp_hz
    p_hp = np.roots([1.0, math.sqrt(2.0) * w0, w0 * w0])
    z = np.zeros(order_s)
    p = np.r_[p_lp, p_hp]
    zd, pd, kd = signal.bilinear_zpk(z, p, k_lp, fs)
    return np.asarray(signal.zpk2sos(zd, pd, kd), dtype=np.float64)


def _unwarp(x: FloatArray, kappa: float) -> FloatArray:
    """x + kappa (x_(k+1) - 2 x_k + x_(k-1)) = x (1 - kappa (w T)^2): the bilinear map's
    frequency warping undone to O((w T)^4) -- |s_b| = w (1 + (w T)^2 / 12): kappa = 1/12
    after one bilinear derivative, 1/6 after two, -1/12 / -1/6 after one / two bilinear
    integrations (the
    accelerometer reads the exact derivative; mixing it with bilinear derivatives of the
    LVDT otherwise biases m and k_t by ~(w T)^2 / 6, 0.1 % at the wheel mode)."""
    d2 = np.zeros_like(x)
    d2[1:-1] = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return np.asarray(x + kappa * d2, dtype=np.float64)


#: the correction of :func:`_unwarp` for a chain column of order j (2 = no derivative)
_KAPPA = {0: -1.0 / 6.0, 1: -1.0 / 12.0, 2: 0.0, 3: 1.0 / 12.0, 4: 1.0 / 6.0}


class _Chain:
    """The filter chain of one fit: x -> s^j P H / s^2 x (j = 0..4)."""

    def __init__(self, fc_hz: float, hp_hz: float, fs: float, lp_order: int = 4) -> None:
        self.sos = [_chain_sos(j, fc_hz, hp_hz, fs, lp_order) for j in range(5)]
        self.fs = fs

    def __call__(self, x: FloatArray, j: int) -> FloatArray:
        return _unwarp(np.asarray(signal.sosfilt(self.sos[j], x), dtype=np.float64),
                       _KAPPA[j])

    def impulse(self, j: int, n: int, pre: tuple[FloatArray, FloatArray] | None = None
                ) -> FloatArray:
        x = np.zeros(n)
        x[0] = 1.0
        if pre is not None:
            x = signal.lfilter(pre[0], pre[1], x)
        return self(x, j)


def _accel_lowpass(cfg: RigConfig, dt: float) -> tuple[FloatArray, FloatArray]:
    """(b, a) of the accelerometer's first-order low-pass (hil.sim.sensors: Tustin,
    pre-warped at the bandwidth); identity when beyond Nyquist."""
    wc = 2.0 * math.pi * cfg.sensors.accel_bandwidth_hz
    if wc >= 0.999 * math.pi / dt:
        return np.array([1.0]), np.array([1.0])
    k = math.tan(wc * dt / 2.0)
    b = k / (1.0 + k)
    return np.array([b, b]), np.array([1.0, (k - 1.0) / (1.0 + k)])


# ---------------------------------------------------------------------------- helpers


def _blocks(idx: NDArray[np.int64], n_blocks: int) -> list[NDArray[np.int64]]:
    return [b for b in np.array_split(idx, n_blocks) if b.size]


def _gram(cols: FloatArray, blocks: list[NDArray[np.int64]]) -> NDArray[np.float64]:
    """Per-block Gram matrices (B, c, c) of the column matrix (n, c)."""
    return np.stack([cols[b].T @ cols[b] for b in blocks])


def _bcls(g: FloatArray, n: float, noise: FloatArray, y: int, xs: list[int],
          weights: FloatArray | None = None) -> FloatArray:
    """Bias-compensated LS of column y on columns xs from a Gram matrix g (summed over n
    samples) and the per-sample noise Gram ``noise``: (Sxx/n - Nxx)^-1 (Sxy/n - Nxy)."""
    sxx = g[np.ix_(xs, xs)] / n - noise[np.ix_(xs, xs)]
    sxy = g[xs, y] / n - noise[xs, y]
    return np.asarray(np.linalg.solve(sxx, sxy), dtype=np.float64)



def _jack_ci(full: float, reps: FloatArray, widen: float = 1.0,
             bias: float = 0.0, se_floor: float = 0.0) -> tuple[float, float, float]:
    """(lo, hi, standard error) of a delete-one-block jackknife; the standard error is
    at least ``se_floor`` (the HAC sandwich's), ``bias`` is added to the half width."""
    b = reps.size
    se = math.sqrt((b - 1) / b * float(np.sum((reps - reps.mean()) ** 2))) * widen
    se = max(se, se_floor)
    half = float(stats.t.ppf(0.975, b - 1)) * se + abs(bias)
    return full - half, full + half, se


def _hac_se(x: FloatArray, e: FloatArray, a: FloatArray, max_lag: int) -> FloatArray:
    """Standard errors of a (bias-compensated) LS estimate with normal matrix ``a``
    (per sample), regressors ``x`` (n, p) and residuals ``e``: Newey-West sandwich with a
    Bartlett window of ``max_lag`` ticks (the residuals and the regressors are coloured by
    the filters and the low-frequency regressors carry long correlations)."""
    n = x.shape[0]
    psi = x * e[:, None]
    psi = psi - psi.mean(0)
    f = np.fft.rfft(psi, 2 * n, axis=0)
    p = x.shape[1]
    omega = np.zeros((p, p))
    lags = np.arange(max_lag)
    w = 1.0 - lags / max_lag
    for i in range(p):
        for j in range(i, p):
            c = np.fft.irfft(f[:, i] * np.conj(f[:, j]), axis=0)
            v = c[0] + float(np.sum(w[1:] * (c[1:max_lag] + c[-1:-max_lag:-1])))
            omega[i, j] = omega[j, i] = v
    ainv = np.linalg.inv(a)
    cov = ainv @ (omega / (n * n)) @ ainv.T
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _corr_time_ticks(res: FloatArray) -> float:
    """Integrated autocorrelation time of a residual [ticks] (Sokal's window)."""
    x = res - res.mean()
    n = x.size
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac = ac / ac[0]
    tau = 1.0
    for k in range(1, n):
        tau += 2.0 * ac[k]
        if k >= 5.0 * tau:
            break
    return max(tau, 1.0)


# ---------------------------------------------------------------------------- checks


def _pieces(data: RunData) -> list[tuple[int, int]]:
    """[start, stop) of the runs the filter chains go through in one piece: a new piece
    starts at every tick without the next sensor sample (a frame missed or held, a loop
    period skipped: the series is not uniformly sampled across it)."""
    n = data.rattlespace_m.size
    if data.fresh is None or np.all(data.fresh):
        return [(0, n)]
    starts = np.unique(np.r_[0, np.flatnonzero(~data.fresh)])
    stops = np.r_[starts[1:], n]
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def _piecewise(pieces: list[tuple[int, int]], fn: Callable[..., FloatArray],
               data: RunData, *arrays: FloatArray) -> FloatArray:
    """``fn(data, *arrays)`` run on every piece separately (the filter chains restart
    after each gap), concatenated back onto the ticks."""
    if len(pieces) == 1:
        return fn(data, *arrays)
    return np.concatenate([fn(_slice(data, a, b), *(x[a:b] for x in arrays))
                           for a, b in pieces])


def _slice(data: RunData, a: int, b: int) -> RunData:
    return replace(data, rattlespace_m=data.rattlespace_m[a:b], accel_mps2=data.accel_mps2[a:b],
                   force_n=data.force_n[a:b], force_ref_n=data.force_ref_n[a:b],
                   spool_cmd=data.spool_cmd[a:b], excite=data.excite[a:b],
                   rest=data.rest[a:b], fresh=None if data.fresh is None else data.fresh[a:b])


def _segments(data: RunData, cfg: RigConfig
              ) -> tuple[NDArray[np.int64], NDArray[np.int64], dict[str, Any]]:
    """The excitation and rest ticks the fit uses, and what the gaps left out."""
    dt = data.dt_s
    excite, rest_mask = data.excite.copy(), data.rest.copy()
    played = np.flatnonzero(data.excite)
    if played.size == 0:
        raise IdentificationRefusedError("no excitation segment: record `rig run --excite` (or "
                                    "`rig demo --excite`); this run has no 'excitation' "
                                    "start event with the valve driven")
    skip = round(1.0 / dt)          # the force loop and the filters settle
    excite[:played[0] + skip] = False
    considered = int(excite.sum())
    pieces = _pieces(data)
    if len(pieces) > 1:
        # the chains restart at each gap: its ticks and the settling after it are out
        assert data.fresh is not None
        settle = round(SEGMENT_SETTLE_S / dt)
        settled = np.ones_like(excite)
        for a, b in pieces[1:]:
            settled[a:min(b, a + settle)] = False
        excite &= settled & data.fresh
        rest_mask &= data.fresh
    exc = np.flatnonzero(excite)
    missed = 0 if data.fresh is None else int(np.sum(~data.fresh & data.excite))
    gaps = int(sum(1 for a, _ in pieces[1:] if data.excite[a]
                   and (a == 0 or data.fresh is None or data.fresh[a - 1])))
    left_out = considered - exc.size
    info = {"missed_sensor_samples": missed, "gaps": gaps,
            "left_out_s": left_out * dt,
            "left_out_fraction": left_out / considered if considered else 0.0,
            "segment_settle_s": SEGMENT_SETTLE_S}
    if exc.size * dt < MIN_EXCITATION_S:
        if left_out and considered * dt >= MIN_EXCITATION_S:
            raise IdentificationRefusedError(
                f"too little data between missed sensor samples: {exc.size * dt:.2f} s of "
                f"the excitation usable, at least {MIN_EXCITATION_S:g} s needed ({missed} "
                f"ticks without fresh SensorData in {gaps} gaps left out "
                f"{left_out * dt:.2f} s with the filters' {SEGMENT_SETTLE_S:g} s settling "
                "after each); rerun with the real-time set-up (`rig check-host`)")
        raise IdentificationRefusedError(
            f"excitation too short: {data.excite.sum() * dt:.2f} s recorded, at least "
            f"{MIN_EXCITATION_S + 1.0:g} s needed (excitation.duration_s "
            f"{cfg.excitation.duration_s:g} s; was it aborted?)")
    rest = np.flatnonzero(rest_mask)
    rest = rest[rest >= rest[0] + round(0.2 / dt)] if rest.size else rest
    if rest.size * dt < MIN_REST_S:
        raise IdentificationRefusedError(
            f"rest too short: {rest.size * dt:.2f} s of passive rest before the excitation, "
            f"at least {MIN_REST_S + 0.2:g} s needed for the sensor offsets and noise")
    return exc, rest, info


def _check_saturation(data: RunData, cfg: RigConfig, exc: NDArray[np.int64]) -> None:
    s = cfg.sensors
    limits = (("spool command", np.abs(data.spool_cmd[exc]),
               0.999 * cfg.force_loop.output_limit),
              ("LVDT", np.abs(data.rattlespace_m[exc]), 0.99 * s.lvdt_range_m),
              ("load cell", np.abs(data.force_n[exc]), 0.99 * s.load_cell_range_n),
              ("accelerometer", np.abs(data.accel_mps2[exc]), 0.99 * s.accel_range_mps2))
    for name, x, lim in limits:
        frac = float(np.mean(x >= lim))
        if frac > SATURATED_FRACTION:
            raise IdentificationRefusedError(
                f"saturated: the {name} is at its limit ({lim:g}) for {100 * frac:.1f} % of "
                "the excitation; lower excitation.chirp_amplitude_n / prbs_amplitude_n")
    if not (np.all(np.isfinite(data.rattlespace_m[exc])) and np.all(np.isfinite(
            data.accel_mps2[exc])) and np.all(np.isfinite(data.force_n[exc]))):
        raise IdentificationRefusedError("the excitation has non-finite sensor readings")


# ---------------------------------------------------------------------------- mechanics

# column order of the mechanical fit
_F0, _A2, _A1, _A0, _R0, _R1, _R2, _Q = range(8)
_N_COLS = 8


def _mech_columns(data: RunData, cfg: RigConfig, offsets: dict[str, float],
                  chain: _Chain, lp: tuple[FloatArray, FloatArray],
                  x2: FloatArray | None = None) -> FloatArray:
    """The mechanical fit's columns, the chains restarted after every gap."""
    pieces = _pieces(data)
    if x2 is None:
        return _piecewise(pieces, lambda d: _mech_piece(d, cfg, offsets, chain, lp), data)
    return _piecewise(pieces, lambda d, x: _mech_piece(d, cfg, offsets, chain, lp, x),
                      data, x2)


def _mech_piece(data: RunData, cfg: RigConfig, offsets: dict[str, float],
                chain: _Chain, lp: tuple[FloatArray, FloatArray],
                x2: FloatArray | None = None) -> FloatArray:
    r = data.rattlespace_m - offsets["r"]
    a = data.accel_mps2 - offsets["a"]
    f = data.force_n - offsets["f"]
    lr = signal.lfilter(lp[0], lp[1], r)
    lf = signal.lfilter(lp[0], lp[1], f)
    cols = np.empty((r.size, _N_COLS))
    cols[:, _F0] = chain(lf, 2)
    cols[:, _A2] = chain(a, 2)
    cols[:, _A1] = chain(a, 1)
    cols[:, _A0] = chain(a, 0)
    cols[:, _R0] = chain(lr, 2)
    cols[:, _R1] = chain(lr, 3)
    cols[:, _R2] = chain(lr, 4)
    # second order of the tire law: (zs + r)^2 about its mean, through the same chain
    # (zs + r from ``x2``, a wider band, when given: squaring needs the whole motion)
    if x2 is None:
        x2 = cols[:, _A0] + cols[:, _R0]
    cols[:, _Q] = chain(x2 * x2 - float(np.mean(x2 * x2)), 2)
    return cols


def _mech_noise(chain: _Chain, lp: tuple[FloatArray, FloatArray], sig: dict[str, float],
                n: int) -> FloatArray:
    """Per-sample Gram of the columns' white sensor noise (impulse responses)."""
    h = np.zeros((_N_COLS, n))
    noise = np.zeros((_N_COLS, _N_COLS))
    for src, spec in (("f", ((_F0, 2, True),)),
                      ("a", ((_A2, 2, False), (_A1, 1, False), (_A0, 0, False))),
                      ("r", ((_R0, 2, True), (_R1, 3, True), (_R2, 4, True)))):
        h[:] = 0.0
        for col, j, pre in spec:
            h[col] = chain.impulse(j, n, lp if pre else None)
        noise += sig[src] ** 2 * (h @ h.T)
    return noise


def _mech_params(gb: FloatArray, g: FloatArray, n: float, noise_b: FloatArray,
                 noise: FloatArray, gravity: float, e_fixed: float | None = None
                 ) -> dict[str, float]:
    """M, K, C (body chain's Gram ``gb``) then m, k_t, c_t, k_2 (total, wheel chain's
    Gram ``g``)."""
    # body: F0 = M a2 - K r0 - C r1
    th = _bcls(gb, n, noise_b, _F0, [_A2, _R0, _R1])
    mass, k, c = th[0], -th[1], -th[2]
    # total: -M a2 = m (a2 + r2) + k_t (a0 + r0) + c_t (a1 + r1) - k_2 Q
    t = np.zeros((5, _N_COLS))
    t[0, _A2] = -mass
    t[1, _A2] = t[1, _R2] = 1.0
    t[2, _A0] = t[2, _R0] = 1.0
    t[3, _A1] = t[3, _R1] = 1.0
    t[4, _Q] = -1.0
    g2 = t @ g @ t.T
    n2 = t @ noise @ t.T
    th2 = _bcls(g2, n, n2, 0, [1, 2, 3, 4])
    m, kt, ct, k2 = (float(x) for x in th2)
    load = (mass + m) * gravity
    e = 1.0 / (1.0 - 2.0 * load * k2 / (kt * kt)) if kt > 0 else math.nan
    if e_fixed is not None:
        # the exponent not resolved: the linear tire alone (no curvature term)
        th3 = _bcls(g2, n, n2, 0, [1, 2, 3])
        m, kt, ct = (float(x) for x in th3)
        k2 = 0.0
        load = (mass + m) * gravity
        e = e_fixed
    return {"M": float(mass), "K": float(k), "C": float(c), "m": m, "kt": kt, "ct": ct,
            "k2": k2, "e": e, "load": load}


def _mech_hac(cols: FloatArray, cols_w: FloatArray, exc: NDArray[np.int64],
              full: dict[str, float], noise_b: FloatArray, noise: FloatArray,
              max_lag: int) -> dict[str, float]:
    """HAC standard errors of M, K, C (body) and m, k_t (total equation)."""
    xb = np.stack([cols[exc, _A2], -cols[exc, _R0], -cols[exc, _R1]], axis=1)
    yb = cols[exc, _F0]
    th = np.array([full["M"], full["K"], full["C"]])
    ib = [_A2, _R0, _R1]
    sgn = np.array([1.0, -1.0, -1.0])
    ab = xb.T @ xb / exc.size - (noise_b[np.ix_(ib, ib)] * np.outer(sgn, sgn))
    se_b = _hac_se(xb, yb - xb @ th, ab, max_lag)
    c = cols_w[exc]
    xw = np.stack([c[:, _A2] + c[:, _R2], c[:, _A0] + c[:, _R0], c[:, _A1] + c[:, _R1],
                   -c[:, _Q]], axis=1)
    yw = -full["M"] * c[:, _A2]
    thw = np.array([full["m"], full["kt"], full["ct"], full["k2"]])
    t = np.zeros((4, _N_COLS))
    t[0, _A2] = t[0, _R2] = 1.0
    t[1, _A0] = t[1, _R0] = 1.0
    t[2, _A1] = t[2, _R1] = 1.0
    t[3, _Q] = -1.0
    aw = xw.T @ xw / exc.size - t @ noise @ t.T
    se_w = _hac_se(xw, yw - xw @ thw, aw, max_lag)
    return {"M": float(se_b[0]), "K": float(se_b[1]), "C": float(se_b[2]),
            "m": float(se_w[0]), "kt": float(se_w[1])}


def _tire_coefficient(kt_lin: float, load: float, e: float) -> float:
    """k' [N/mm^e] of f = k' (1000 x2)^e with slope kt_lin at the static load."""
    x2s = e * load / kt_lin
    return float(load / (1000.0 * x2s) ** e)


# ---------------------------------------------------------------------------- actuator

_A_DF, _A_F, _A_DR, _A_V = range(4)


def _actuator_columns(data: RunData, cfg: RigConfig, offsets: dict[str, float],
                      chain: _Chain, tau: float, delay: int) -> FloatArray:
    """The actuator fit's columns, the chains restarted after every gap."""
    return _piecewise(_pieces(data),
                      lambda d: _actuator_piece(d, cfg, offsets, chain, tau, delay), data)


def _actuator_piece(data: RunData, cfg: RigConfig, offsets: dict[str, float],
                    chain: _Chain, tau: float, delay: int) -> FloatArray:
    """Columns of the interval form of the pressure equation over [t_{k-1}, t_k]:
    (F_k - F_{k-1}) / T = -beta (F_k + F_{k-1}) / 2 + k_h (r_k - r_{k-1}) / T + gamma v_k,
    v_k the valve term of the spool's exact mean over the interval (command held,
    first-order lag ``tau``, ``delay`` ticks late), all through one band-pass."""
    act = cfg.actuator
    dt = data.dt_s
    f = data.force_n - offsets["f"]
    r = data.rattlespace_m - offsets["r"]
    u = np.r_[np.zeros(delay), data.spool_cmd[:data.spool_cmd.size - delay]]
    p = math.exp(-dt / tau)
    xv = signal.lfilter([0.0, 1.0 - p], [1.0, -p], u)         # x_v at the ticks
    u_prev = np.r_[0.0, u[:-1]]
    xv_prev = np.r_[0.0, xv[:-1]]
    xbar = u_prev + (xv_prev - u_prev) * (tau / dt) * (1.0 - p)
    fmid = 0.5 * (f + np.r_[f[0], f[:-1]])
    drop = act.supply_pressure_pa - np.sign(xbar) * fmid / act.piston_area_m2
    v = act.piston_area_m2 * act.spool_stroke_m * xbar * np.sign(drop) * np.sqrt(
        np.abs(drop))
    cols = np.empty((f.size, 4))
    cols[:, _A_DF] = chain(np.r_[0.0, np.diff(f)] / dt, 2)
    cols[:, _A_F] = chain(fmid, 2)
    cols[:, _A_DR] = chain(np.r_[0.0, np.diff(r)] / dt, 2)
    cols[:, _A_V] = chain(v, 2)
    return cols


def _actuator_noise(chain: _Chain, sig: dict[str, float], n: int, dt: float) -> FloatArray:
    """Per-sample noise Gram of the actuator columns (white load cell and LVDT noise)."""
    noise = np.zeros((4, 4))
    h = np.zeros((4, n))
    diff = (np.array([1.0, -1.0]) / dt, np.array([1.0]))
    mid = (np.array([0.5, 0.5]), np.array([1.0]))
    h[_A_DF] = chain.impulse(2, n, diff)
    h[_A_F] = chain.impulse(2, n, mid)
    noise += sig["f"] ** 2 * (h @ h.T)
    h[:] = 0.0
    h[_A_DR] = chain.impulse(2, n, diff)
    noise += sig["r"] ** 2 * (h @ h.T)
    return noise


def _act_solve(g: FloatArray, n: float, noise: FloatArray) -> tuple[FloatArray, float]:
    th = _bcls(g, n, noise, _A_DF, [_A_F, _A_DR, _A_V])
    x = [_A_F, _A_DR, _A_V]
    rss = float(g[_A_DF, _A_DF] / n - 2 * th @ g[x, _A_DF] / n + th @ (g[np.ix_(x, x)] / n) @ th)
    return th, rss


def _identify_actuator(data: RunData, cfg: RigConfig, offsets: dict[str, float],
                       sig: dict[str, float], exc: NDArray[np.int64],
                       blocks: list[NDArray[np.int64]], delay: int,
                       lowpass_hz: float = ACTUATOR_LOWPASS_HZ) -> dict[str, Any]:
    fs = 1.0 / data.dt_s
    chain = _Chain(min(lowpass_hz, 0.4 * fs), HIGHPASS_HZ, fs, lp_order=2)
    noise = _actuator_noise(chain, sig, 4096, data.dt_s)
    taus = np.geomspace(1e-4, 2e-2, 41)
    n = float(exc.size)
    best: tuple[float, int] = (math.inf, 0)
    grams: dict[int, FloatArray] = {}
    for d in (delay,):
        gs = np.stack([_gram(_actuator_columns(data, cfg, offsets, chain, float(t), d),
                             blocks) for t in taus])        # (T, B, 4, 4)
        grams[d] = gs
        rss = np.array([_act_solve(gs[i].sum(0), n, noise)[1] for i in range(taus.size)])
        if rss.min() < best[0]:
            best = (float(rss.min()), d)
    d = best[1]
    gs = grams[d]

    def fit(g_of_tau: FloatArray, nn: float) -> tuple[float, FloatArray]:
        rss = np.array([_act_solve(g_of_tau[i], nn, noise)[1] for i in range(taus.size)])
        i = int(np.argmin(rss))
        lt = np.log(taus)
        if 0 < i < taus.size - 1:     # parabola through the three points about the minimum
            y0, y1, y2 = rss[i - 1], rss[i], rss[i + 1]
            den = y0 - 2 * y1 + y2
            step = lt[1] - lt[0]
            off = 0.5 * (y0 - y2) / den if den > 0 else 0.0
            ltau = lt[i] + float(np.clip(off, -1.0, 1.0)) * step
        else:
            ltau = lt[i]
        j = int(np.clip(np.searchsorted(lt, ltau), 1, taus.size - 1))
        w = (ltau - lt[j - 1]) / (lt[j] - lt[j - 1])
        gi = (1 - w) * g_of_tau[j - 1] + w * g_of_tau[j]
        th, _ = _act_solve(gi, nn, noise)
        return math.exp(ltau), th

    total = gs.sum(1)
    tau, th = fit(total, n)
    reps = []
    for b, blk in enumerate(blocks):
        tb, thb = fit(total - gs[:, b], n - blk.size)
        reps.append([tb, *thb])
    rep = np.array(reps)
    return {"tau": tau, "beta": float(th[0]), "kh": float(th[1]), "gamma": float(th[2]),
            "delay_ticks": d, "reps": rep, "at_grid_edge": tau <= taus[0] * 1.01
            or tau >= taus[-1] / 1.01}


# ---------------------------------------------------------------------------- frequency


def model_frequency_response(mass: float, m: float, k: float, c: float, kt: float,
                             ct: float, f_hz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(F -> zs'', F -> r) complex responses of the linear quarter car with the road at
    rest (python-control), F the actuator force."""
    import control

    a = np.array([[0.0, 0.0, 1.0, 0.0],
                  [0.0, 0.0, 0.0, 1.0],
                  [-k / mass, k / mass, -c / mass, c / mass],
                  [k / m, -(k + kt) / m, c / m, -(c + ct) / m]])
    b = np.array([[0.0], [0.0], [1.0 / mass], [-1.0 / m]])
    cm = np.array([a[2], [-1.0, 1.0, 0.0, 0.0]])
    dm = np.array([[1.0 / mass], [0.0]])
    sys = control.ss(a, b, cm, dm)
    resp = control.frequency_response(sys, 2 * np.pi * np.asarray(f_hz))
    h = np.asarray(resp.frdata)     # (outputs, inputs, freqs)
    return h[0, 0], h[1, 0]


def _welch_frf(data: RunData, exc: NDArray[np.int64], offsets: dict[str, float],
               lp: tuple[FloatArray, FloatArray], cfg: RigConfig) -> dict[str, FloatArray]:
    fs = 1.0 / data.dt_s
    ref = data.force_ref_n[exc]
    nper = min(4096, 1 << int(math.log2(max(exc.size // 4, 256))))
    kw = {"fs": fs, "nperseg": nper, "noverlap": nper // 2}
    f, prr = signal.welch(ref, **kw)
    out: dict[str, FloatArray] = {"f_hz": f}
    for name, x in (("a", data.accel_mps2[exc] - offsets["a"]),
                    ("r", data.rattlespace_m[exc] - offsets["r"]),
                    ("F", data.force_n[exc] - offsets["f"])):
        _, pxr = signal.csd(ref, x, **kw)
        out["H_" + name] = pxr / prr
        _, coh = signal.coherence(ref, x, **kw)
        out["coh_" + name] = coh
    # the accelerometer's low-pass out of its response
    _, lpa = signal.freqz(lp[0], lp[1], worN=f, fs=fs)
    out["H_a"] = out["H_a"] / lpa
    return out


def _frequency_fit(frf: dict[str, FloatArray], lo: float, hi: float) -> dict[str, float]:
    """M, K, C from M H_a - (K + j w C) H_r = H_F over [lo, hi] Hz (coherent bins)."""
    f = frf["f_hz"]
    sel = (f >= lo) & (f <= hi) & (frf["coh_F"] > 0.8) & (frf["coh_r"] > 0.8) \
        & (frf["coh_a"] > 0.8)
    w = 2 * np.pi * f[sel]
    ha, hr, hf = frf["H_a"][sel], frf["H_r"][sel], frf["H_F"][sel]
    x = np.stack([ha, -hr, -1j * w * hr], axis=1)
    xr = np.vstack([x.real, x.imag])
    yr = np.r_[hf.real, hf.imag]
    scale = np.abs(xr).max(axis=0)
    th, *_ = np.linalg.lstsq(xr / scale, yr, rcond=None)
    th = th / scale
    return {"M": float(th[0]), "K": float(th[1]), "C": float(th[2]), "bins": int(sel.sum())}


# ---------------------------------------------------------------------------- main


_KEYS = {"M": "vehicle.sprung_mass_kg", "m": "vehicle.unsprung_mass_kg",
         "K": "vehicle.suspension_stiffness_n_per_m",
         "C": "vehicle.suspension_damping_ns_per_m",
         "kprime": "tire.stiffness_coefficient", "e": "tire.stiffness_exponent",
         "fo": "sensors.load_cell_offset_n", "ab": "sensors.accel_bias_mps2",
         "tau": "actuator.spool_time_constant_s", "alpha": "actuator.alpha_n_per_m5",
         "beta": "actuator.leakage_beta_per_s", "gamma": "actuator.valve_gamma"}


def identify(data: RunData, cfg: RigConfig, n_blocks: int = N_BLOCKS) -> Identification:
    """Identify the rig from one identification run (see the module docstring);
    :class:`IdentificationRefusedError` names why a run cannot be used."""
    dt = data.dt_s
    fs = 1.0 / dt
    exc, rest, gaps = _segments(data, cfg)
    _check_saturation(data, cfg, exc)
    offsets = {"r": float(np.mean(data.rattlespace_m[rest])),
               "a": float(np.mean(data.accel_mps2[rest])),
               "f": float(np.mean(data.force_n[rest]))}
    sig = {"r": float(np.std(data.rattlespace_m[rest])),
           "a": float(np.std(data.accel_mps2[rest])),
           "f": float(np.std(data.force_n[rest]))}
    lp = _accel_lowpass(cfg, dt)
    chain = _Chain(min(LOWPASS_HZ, 0.4 * fs), HIGHPASS_HZ, fs)
    cols = _mech_columns(data, cfg, offsets, chain, lp)
    noise_b = _mech_noise(chain, lp, sig, round(fs / HIGHPASS_HZ))
    chain_w = _Chain(min(WHEEL_LOWPASS_HZ, 0.4 * fs), WHEEL_HIGHPASS_HZ, fs)
    cols_w = _mech_columns(data, cfg, offsets, chain_w, lp, cols[:, _A0] + cols[:, _R0])
    noise = _mech_noise(chain_w, lp, sig, round(fs / WHEEL_HIGHPASS_HZ))
    blocks = _blocks(exc, n_blocks)
    grams_b = _gram(cols, blocks)
    grams = _gram(cols_w, blocks)
    total_b = grams_b.sum(0)
    total = grams.sum(0)
    n = float(exc.size)
    g = cfg.vehicle.gravity_mps2
    full = _mech_params(total_b, total, n, noise_b, noise, g)
    reps = [_mech_params(total_b - grams_b[b], total - grams[b], n - blk.size, noise_b,
                         noise, g) for b, blk in enumerate(blocks)]
    # uncompensated fit: the size of the noise-induced bias the compensation removed
    raw = _mech_params(total_b, total, n, np.zeros_like(noise), np.zeros_like(noise), g)
    # the same fit in a second pair of bands: model and discretisation errors depend on
    # the band, noise does not average them out; the spread joins the interval
    chain_b2 = _Chain(min(ALT_LOWPASS_HZ, 0.4 * fs), ALT_HIGHPASS_HZ, fs)
    cols_b2 = _mech_columns(data, cfg, offsets, chain_b2, lp)
    chain_w2 = _Chain(min(ALT_WHEEL_LOWPASS_HZ, 0.4 * fs), ALT_WHEEL_HIGHPASS_HZ, fs)
    cols_w2 = _mech_columns(data, cfg, offsets, chain_w2, lp,
                            cols[:, _A0] + cols[:, _R0])
    alt_noise_b = _mech_noise(chain_b2, lp, sig, round(fs / ALT_HIGHPASS_HZ))
    alt_noise = _mech_noise(chain_w2, lp, sig, round(fs / ALT_WHEEL_HIGHPASS_HZ))
    alt = _mech_params(cols_b2[exc].T @ cols_b2[exc], cols_w2[exc].T @ cols_w2[exc], n,
                       alt_noise_b, alt_noise, g)
    hac = _mech_hac(cols, cols_w, exc, full, noise_b, noise, round(HAC_LAG_S * fs))

    # wheel on the ground throughout?
    tire_load = full["load"] + full["M"] * cols_w[exc, _A2] + full["m"] * (
        cols_w[exc, _A2] + cols_w[exc, _R2])
    low = float(tire_load.min())
    if low < MIN_TIRE_LOAD_FRACTION * full["load"]:
        t_low = float(exc[int(np.argmin(tire_load))] * dt)
        raise IdentificationRefusedError(
            f"wheel off the ground: the tire load fell to {low:.0f} N of the static "
            f"{full['load']:.0f} N at t = {t_low:.2f} s; lower excitation.chirp_amplitude_n")

    # correlation of the residuals across blocks: widen by sqrt(corr. time / block)
    body_res = cols[exc, _F0] - (full["M"] * cols[exc, _A2] - full["K"] * cols[exc, _R0]
                                 - full["C"] * cols[exc, _R1])
    tau_c = _corr_time_ticks(body_res)
    block_len = exc.size / len(blocks)
    widen = math.sqrt(1.0 + tau_c / block_len)

    estimates: dict[str, float] = {}
    ci: dict[str, tuple[float, float]] = {}
    not_id: dict[str, str] = {}
    se: dict[str, float] = {}

    def put(name: str, value: float, rep_values: FloatArray, bias: float = 0.0,
            se_floor: float = 0.0) -> None:
        lo, hi, s = _jack_ci(value, rep_values, widen, bias, se_floor)
        estimates[_KEYS[name]] = value
        ci[_KEYS[name]] = (lo, hi)
        se[_KEYS[name]] = s

    # tire exponent: identified only when its interval is narrow
    e_reps = np.array([r["e"] for r in reps])
    e_lo, e_hi, _ = _jack_ci(full["e"], e_reps, widen)
    e_cfg = cfg.tire.stiffness_exponent
    x2_rms = float(np.std(cols[exc, _A0] + cols[exc, _R0]))
    x2s_cfg = e_cfg * full["load"] / full["kt"]
    e_ok = (math.isfinite(full["e"]) and 1.0 <= full["e"] <= 3.0
            and (e_hi - e_lo) / 2.0 <= EXPONENT_HALF_WIDTH
            and x2_rms >= MIN_RELATIVE_DEFLECTION * x2s_cfg)
    if e_ok:
        put("e", full["e"], e_reps)
        e_use = full["e"]
        kp_reps = np.array([_tire_coefficient(r["kt"], r["load"], r["e"]) for r in reps])
    else:
        not_id[_KEYS["e"]] = (
            f"not identified: the tire deflection varied by {1e3 * x2_rms:.2f} mm RMS about "
            f"a static {1e3 * x2s_cfg:.1f} mm ({100 * x2_rms / x2s_cfg:.0f} %); the tire "
            f"law's curvature needs >= {100 * MIN_RELATIVE_DEFLECTION:.0f} % and a 95 % "
            f"interval within +/-{EXPONENT_HALF_WIDTH} to be told from the tire damping's "
            f"nonlinearity; tire.stiffness_coefficient is given for the configured exponent "
            f"{e_cfg:g}")
        e_use = e_cfg
        # the tire fit again with the configured curvature as a known term
        full_e = _mech_params(total_b, total, n, noise_b, noise, g, e_cfg)
        reps_e = [_mech_params(total_b - grams_b[b], total - grams[b], n - blk.size,
                               noise_b, noise, g, e_cfg) for b, blk in enumerate(blocks)]
        alt = _mech_params(cols_b2[exc].T @ cols_b2[exc], cols_w2[exc].T @ cols_w2[exc], n,
                           alt_noise_b, alt_noise, g, e_cfg)
        for key in ("m", "kt", "ct", "load"):
            full[key] = full_e[key]
            for r, re_ in zip(reps, reps_e, strict=True):
                r[key] = re_[key]
        kp_reps = np.array([_tire_coefficient(r["kt"], r["load"], e_cfg) for r in reps])
    for name in ("M", "K", "C", "m"):
        # the bias compensation is uncertain by the noise Gram's own error (noise levels
        # from a short rest): a tenth of the correction is added to the interval, and
        # the spread over the two bands
        put(name, full[name], np.array([r[name] for r in reps]),
            0.1 * abs(full[name] - raw[name]) + abs(full[name] - alt[name]), hac[name])
    kprime = _tire_coefficient(full["kt"], full["load"], e_use)
    # delta method from the HAC errors of k_t and the static load: k' ~ L^(1-e) k_t^e
    rel = math.hypot(e_use * hac["kt"] / full["kt"],
                     (e_use - 1.0) * math.hypot(hac["M"], hac["m"]) / (full["M"] + full["m"]))
    kp_alt = _tire_coefficient(alt["kt"], alt["load"], e_use)
    # the linear tire model leaves out the law's third-order term; its effect on the
    # slope fitted to deflections with moments E[x^4] / E[x^2] about x2s is
    # (e - 1)(e - 2) / 6 E[x^4] / (E[x^2] x2s^2) of k_t, e times that of k'
    x2 = cols[exc, _A0] + cols[exc, _R0]
    x2s = e_use * full["load"] / full["kt"]
    third = abs((e_use - 1.0) * (e_use - 2.0)) / 6.0 * float(
        np.mean(x2 ** 4) / np.mean(x2 ** 2)) / x2s ** 2
    put("kprime", kprime, kp_reps, abs(kprime - kp_alt) + e_use * third * kprime,
        rel * kprime)
    # sensor offsets: rest means, block jackknife over the rest
    rest_blocks = _blocks(rest, 10)
    for name, ch, key in (("fo", data.force_n, "f"), ("ab", data.accel_mps2, "a")):
        means = np.array([np.mean(np.delete(ch[rest], np.s_[b[0] - rest[0]:
                                                           b[-1] - rest[0] + 1]))
                          for b in rest_blocks])
        value = offsets[key]
        lo, hi, s = _jack_ci(value, means)
        estimates[_KEYS[name]] = value
        ci[_KEYS[name]] = (lo, hi)
        se[_KEYS[name]] = s

    # actuator
    delay = cfg.design.compute_delay_ticks
    acts = [_identify_actuator(data, cfg, offsets, sig, exc, blocks, delay, band)
            for band in ACTUATOR_BANDS_HZ]
    act = acts[len(acts) // 2]
    area2 = cfg.actuator.piston_area_m2 ** 2

    def act_values(a: dict[str, Any]) -> dict[str, float]:
        return {"tau": a["tau"], "alpha": a["kh"] / area2, "beta": a["beta"],
                "gamma": a["gamma"]}

    values = act_values(act)
    spread = {k: max(act_values(a)[k] for a in acts) - min(act_values(a)[k] for a in acts)
              for k in values}
    rep_cols = {"tau": act["reps"][:, 0], "alpha": act["reps"][:, 2] / area2,
                "beta": act["reps"][:, 1], "gamma": act["reps"][:, 3]}
    for name, value in values.items():
        lo, hi, s = _jack_ci(value, rep_cols[name], widen, spread[name])
        key = _KEYS[name]
        half = (hi - lo) / 2.0
        if name == "tau" and act["at_grid_edge"]:
            not_id[key] = (f"not identified: the best spool lag {value:.2e} s is at the edge "
                           "of the searched range [1e-4, 2e-2] s")
        elif not (math.isfinite(value) and value > 0 and half <= RELATIVE_HALF_WIDTH * value):
            not_id[key] = (f"not identified: estimate {value:.3g} with 95 % interval "
                           f"[{lo:.3g}, {hi:.3g}] (jackknife + its spread over the bands "
                           f"{'/'.join(f'{b:g}' for b in ACTUATOR_BANDS_HZ)} Hz), wider "
                           f"than +/-{100 * RELATIVE_HALF_WIDTH:.0f} % or not positive: "
                           "the excitation does not separate it")
        else:
            estimates[key] = value
            ci[key] = (lo, hi)
            se[key] = s
    for name in ("damping_c2", "damping_c3"):
        not_id[f"tire.{name}"] = (
            "not identified: only the equivalent linear tire damping at the static "
            f"deflection is resolved ({full['ct']:.0f} Ns/m, fit.tire_damping_ns_per_m)")

    # frequency domain cross-check
    frf = _welch_frf(data, exc, offsets, lp, cfg)
    ex = cfg.excitation
    fd = _frequency_fit(frf, max(ex.chirp_start_hz * 1.5, 0.6), min(ex.chirp_stop_hz, 25.0))
    fd_diff = {k: (fd[k] - full[k]) / full[k] for k in ("M", "K", "C")}
    f_hz = frf["f_hz"]
    h_a_model, h_r_model = model_frequency_response(full["M"], full["m"], full["K"],
                                                    full["C"], full["kt"], full["ct"], f_hz)
    fitted_force = (full["M"] * cols[:, _A2] - full["K"] * cols[:, _R0]
                    - full["C"] * cols[:, _R1])
    rms_res = float(np.sqrt(np.mean(body_res ** 2)))
    rms_f = float(np.sqrt(np.mean(cols[exc, _F0] ** 2)))
    fit: dict[str, Any] = {
        "method": "equation-error least squares, bias-compensated, on filtered signals "
                  f"(body {HIGHPASS_HZ}-{LOWPASS_HZ} Hz, wheel {WHEEL_HIGHPASS_HZ}-"
                  f"{WHEEL_LOWPASS_HZ} Hz); 95 % intervals: delete-one-block jackknife over "
                  f"{len(blocks)} blocks, t({len(blocks) - 1}), widened x{widen:.3f} for "
                  f"residual correlation (time {tau_c * dt * 1e3:.1f} ms), at least the HAC "
                  f"error ({HAC_LAG_S:g} s window), plus the spread over a second pair of "
                  f"bands",
        "excitation_s": exc.size * dt, "rest_s": rest.size * dt,
        "missed_sensor_samples": gaps["missed_sensor_samples"],
        "gaps": gaps,
        "body_residual_rms_n": rms_res, "body_force_rms_n": rms_f,
        "body_fit_r2": 1.0 - (rms_res / rms_f) ** 2 if rms_f > 0 else math.nan,
        "tire_stiffness_linear_n_per_m": full["kt"],
        "tire_damping_ns_per_m": full["ct"],
        "tire_exponent_curvature_fit": full["e"] if e_ok else None,
        "tire_static_load_n": full["load"],
        "tire_load_min_n": low,
        "tire_deflection_rms_m": x2_rms,
        "effective_hydraulic_stiffness_n_per_m": act["kh"],
        "actuator_delay_ticks": act["delay_ticks"],
        "actuator_band_estimates": {f"{b:g}_hz": act_values(a)
                                    for b, a in zip(ACTUATOR_BANDS_HZ, acts, strict=True)},
        "lvdt_rest_reading_m": offsets["r"],
        "noise_std": {"rattlespace_m": sig["r"], "accel_mps2": sig["a"],
                      "force_n": sig["f"]},
        "bias_correction_relative": {k: (full[k] - raw[k]) / full[k] for k in ("M", "K", "C",
                                                                              "m")},
        "standard_error": se,
        "frequency_domain": {"vehicle.sprung_mass_kg": fd["M"],
                             "vehicle.suspension_stiffness_n_per_m": fd["K"],
                             "vehicle.suspension_damping_ns_per_m": fd["C"],
                             "relative_difference": {_KEYS[k]: v for k, v in fd_diff.items()},
                             "bins": fd["bins"]},
        "not_identified": not_id,
    }
    curves = {"f_hz": f_hz, "H_a_meas": frf["H_a"] / frf["H_F"],
              "H_r_meas": frf["H_r"] / frf["H_F"], "coh_a": frf["coh_a"],
              "coh_r": frf["coh_r"], "H_a_model": h_a_model, "H_r_model": h_r_model,
              "t_s": exc * dt, "force_filtered_n": cols[exc, _F0],
              "force_fitted_n": fitted_force[exc], "residual_n": body_res,
              "rattlespace_m": data.rattlespace_m[exc], "accel_mps2": data.accel_mps2[exc],
              "force_n": data.force_n[exc]}
    return Identification(estimates, ci, not_id, fit, curves)


def fitted_config(cfg: RigConfig, ident: Identification) -> RigConfig:
    """``cfg`` with the identified values (keys as in ``ident.estimates``); a non-nominal
    ``[emulator]`` is re-expressed about the fitted values so that the emulated rig
    stays the same plant (clamped to the scales' ranges)."""
    sections: dict[str, dict[str, Any]] = {}
    for key, value in ident.estimates.items():
        sec, name = key.split(".", 1)
        sections.setdefault(sec, {})[name] = float(value)
    em = cfg.emulator
    if not em.is_nominal:
        v, new = cfg.vehicle, sections.get("vehicle", {})

        def rescale(scale: float, old: float, fitted: float | None) -> float:
            return float(min(4.0, max(0.25, scale * old / fitted))) if fitted else scale

        tire = sections.get("tire", {})
        sections["emulator"] = {
            "sprung_mass_scale": rescale(em.sprung_mass_scale, v.sprung_mass_kg,
                                         new.get("sprung_mass_kg")),
            "unsprung_mass_scale": rescale(em.unsprung_mass_scale, v.unsprung_mass_kg,
                                           new.get("unsprung_mass_kg")),
            "spring_rate_scale": rescale(em.spring_rate_scale, v.suspension_stiffness_n_per_m,
                                         new.get("suspension_stiffness_n_per_m")),
            "damping_scale": rescale(em.damping_scale, v.suspension_damping_ns_per_m,
                                     new.get("suspension_damping_ns_per_m")),
            "tire_stiffness_scale": rescale(em.tire_stiffness_scale,
                                            cfg.tire.stiffness_coefficient,
                                            tire.get("stiffness_coefficient")),
        }
    return cfg.replace(**sections)
