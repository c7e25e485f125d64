"""Road preview for the travel schedule: predict the LVDT reading from the road the rig
is about to play (docs/design.md §12).

A shaker rig knows the profile it will play, so the road velocity of the next H seconds
can be an input of the controller.  The schedule's usage envelope reacts to the reading
only once the road has asked for travel; the wheel passes a road edge to the
rattlespace within about a quarter wheel-hop period, too fast for that.  With a preview
the schedule can instead turn to the travel law *before* a predicted excursion and run
the comfort law alone the rest of the time.

The prediction is the *no-force* linear quarter car at the static tire deflection
(secant tire stiffness and tire damping there) of the bank layer the bank runs (its
sprung mass, spring rate, damping and tire; the configured unsprung mass), discretised
with the road velocity held over each tick::

    x_{k+1} = Phi x_k + Gamma w'_k        r = c x = x1 - x2

from the bank's estimate x_k (the blended deviation of its models from their own
equilibria) and the
previewed road velocity w'_k .. w'_{k+H-1}.  The predicted LVDT reading j ticks ahead is

    r_pred(j) = r_meas + (c Phi^j - c) x_k + sum_{i<j} c Phi^{j-1-i} Gamma w'_{k+i}

(the measured reading carries the LVDT zero and the stops' centre; the model supplies
only the change).  The law's own future force is left out on purpose: on the emulated
rig the comfort law's force does not arrive as an ideal force would on a fast
compression (force loop, valve flow), and a closed-loop prediction under-read every
excursion measured, while the no-force one read them (docs/design.md §12).  The force
the actuator delivers *now* (the load cell's) may be added, fading with the time
constant ``design.preview_force_decay_s`` (0 = left out)::

    r_pred(j) += sum_{i<j} c Phi^{j-1-i} Gamma_u lam^i F_meas,   lam = exp(-T / tau)

(``Gamma_u`` the force input of the same model, held over each tick): the force the
body is already being pushed with, which the prediction without it reads as if it
stopped at once.

How far to trust the prediction depends on the layer (:func:`layers_inside_grid`):
inside the grid in spring rate and damping the force is added and the travel law is
called beyond ``design.preview_trigger_inner_m``; on that edge, where the plant may lie
beyond the models, the prediction is the no-force one and the trigger the lower
``preview_trigger_m``, which the travel governor of weight set 2 keeps on every layer.

The same predictor, without force and over the first ``design.preview_clamp_horizon_s``
(50 ms), drives the stop clamp (:func:`clamp_force_bounds_n`), for every law, while the
clamp's own 50 ms predictions have come true (``preview_clamp_trust_m``) and the wheel is
on the road (``controller.runtime.bank._clamp_check``; docs/design.md §12, "The stop
clamp").  It bounds the force so that the predicted reading stays within
``design.preview_stop_clamp_m`` of the stops' centre: with ``brake_rows`` the reading's
response to a force held from the next tick on (arriving through a first-order lag of
half the reaction time ``design.stop_barrier_lag_s``), the force toward a stop is at most
what keeps each look-ahead prediction inside, and where the no-force prediction already
reaches the stop the force is at least what brings it back inside, up to the barrier's
braking force (``design.preview_clamp_brake``, ``stop_barrier_force_fraction``; off: the
force toward that stop is clipped to 0 and no more).  Without a live preview the road is
taken at rest (the state's momentum alone: ``design.stop_clamp_road_at_rest``).

:func:`road_preview` designs the predictor offline into plain arrays;
:func:`predicted_peak_m` and :func:`clamp_force_bounds_n` are the per-tick kernels (numba,
allocate nothing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from controller.arrays import FloatArray
from controller.config import LAYER_KEYS, RigConfig, design_config_hash, layer_config, layer_grid
from controller.human_filter import discretize_zoh
from controller.memo import memoised
from controller.plant import (
    linear_model,
    static_tire_deflection_m,
    tire_damping_ns_per_m,
    tire_secant_stiffness_n_per_m,
)

__all__ = ["CLAMP_TRUST_WINDOW_S", "EDGE_KEYS", "RoadPreview", "cached_road_preview",
           "clamp_force_bounds_n", "layer_triggers_m", "layers_inside_grid",
           "predicted_peak_m", "road_preview"]


@dataclass(frozen=True)
class RoadPreview:
    """The predictor of :func:`road_preview` (SI units), one per layer of the bank.

    ``rows`` (L, P, 4): c Phi^j - c of layer l at the checked look-ahead ticks ``ticks``
    (P,), so that ``rows[l, p] @ dx`` is the state's part of the predicted change of the
    reading; ``impulse`` (L, H): c Phi^m Gamma, m = 0 .. H-1, the reading's response m
    ticks after a tick of unit road velocity [m per (m/s)]; ``force_rows`` (L, P): the
    reading's change at ``ticks`` per newton of the load-cell force measured now, fading
    with ``design.preview_force_decay_s`` [m/N] (zeros when that is 0, and on an edge
    layer under an inner trigger: the no-force prediction); ``brake_rows`` (L, P): the
    reading's change at ``ticks`` per newton of force reference held from the next tick
    on, delivered from 0 through a first-order lag of half ``design.stop_barrier_lag_s``
    (the force loop's rise; the stop clamp's force bound) [m/N]; ``horizon_ticks`` H =
    ``ticks[-1]``; ``trigger_m`` (L,): predicted distance from the stops' centre that
    calls the travel law while layer l runs (``design.preview_trigger_m`` on the grid's
    edge, ``preview_trigger_inner_m`` inside it: :func:`layer_triggers_m`);
    ``edge_trigger_m``: ``preview_trigger_m``, the travel governor's on every layer (with
    the no-force prediction); ``clamp_m``: ``design.preview_stop_clamp_m``, the
    predicted distance from the stops' centre at which the stop clamp clips the force
    toward that stop, over the first ``clamp_points`` look-ahead ticks (the ones within
    ``design.preview_clamp_horizon_s``; 0: the clamp is off).  Layer l is the bank's
    (:func:`controller.config.layer_grid`: its sprung mass, spring rate, damping and
    tire), so the prediction follows the layer the bank runs.
    """

    rows: FloatArray
    ticks: NDArray[np.int64]
    impulse: FloatArray
    force_rows: FloatArray
    brake_rows: FloatArray
    horizon_ticks: int
    trigger_m: FloatArray
    edge_trigger_m: float
    clamp_m: float = 0.0
    clamp_points: int = 0


def _layer_predictor(cfg: RigConfig, ticks: NDArray[np.int64], horizon: int
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """(rows (P, 4), impulse (H,), force_rows (P,), brake_rows (P,)) of the model of
    ``cfg``'s rig."""
    x2 = static_tire_deflection_m(cfg)
    lm = linear_model(cfg.vehicle, tire_secant_stiffness_n_per_m(x2, cfg.tire),
                      tire_damping_ns_per_m(x2, cfg.tire))
    dt = cfg.sample_time_s
    phi, gamma = discretize_zoh(lm.A, lm.B1, dt)
    _, gamma_u = discretize_zoh(lm.A, lm.B2, dt)
    c = lm.C_meas[0]                    # the LVDT row: x1 - x2
    impulse = np.zeros(horizon)
    force_impulse = np.zeros(horizon)   # c Phi^m Gamma_u
    powers = np.zeros((horizon + 1, c.size))
    row = c.copy()
    for m in range(horizon + 1):
        powers[m] = row                 # c Phi^m
        if m < horizon:
            impulse[m] = row @ gamma
            force_impulse[m] = row @ gamma_u
        row = row @ phi
    force_rows = np.zeros(ticks.size)
    tau = cfg.design.preview_force_decay_s
    if tau > 0.0:
        fade = np.exp(-dt / tau) ** np.arange(horizon)     # the force of tick i: lam^i
        for p, j in enumerate(ticks):
            force_rows[p] = force_impulse[:j][::-1] @ fade[:j]
    # a force reference held from the next tick on, delivered through the force loop's lag
    lag = 0.5 * cfg.design.stop_barrier_lag_s
    delivered = 1.0 - np.exp(-dt * np.arange(1, horizon + 1) / lag)
    brake_rows = np.array([force_impulse[:j][::-1] @ delivered[:j] for j in ticks])
    return powers[ticks] - c[None, :], impulse, force_rows, brake_rows


#: the layer keys whose grid edge makes a layer an edge layer (:func:`layers_inside_grid`)
EDGE_KEYS = ("spring_rate_scales", "damping_scales")


def layers_inside_grid(cfg: RigConfig) -> NDArray[np.bool_]:
    """Which layers of ``cfg``'s bank (L,), in the order of
    :func:`controller.config.layer_grid`, lie inside its grid: in each of
    :data:`EDGE_KEYS` with more than one scale, neither the smallest nor the largest.

    The bank runs an edge layer when the plant is there *or beyond*, and in spring rate
    and damping it cannot tell which: the sprung-mass estimator fits them with a prior at
    the configured values (docs/design.md §10), so a plant beyond the grid reads as its
    edge.  The sprung mass itself is measured (§10) and the tire by its wheel hop (§11):
    a layer on their edge is a plant measured there, not a guess."""
    grid = layer_grid(cfg)
    axes = [(min(s), max(s)) for s in zip(*grid, strict=True)]
    keys = [LAYER_KEYS.index(k) for k in EDGE_KEYS]
    return np.array([not any(axes[i][0] < axes[i][1] and scales[i] in axes[i]
                             for i in keys)
                     for scales in grid], dtype=np.bool_)


def layer_triggers_m(cfg: RigConfig) -> FloatArray:
    """The road preview's trigger [m] of each layer of ``cfg``'s bank (L,):
    ``design.preview_trigger_inner_m`` for a layer inside the grid
    (:func:`layers_inside_grid`), ``design.preview_trigger_m`` on its edge, where the
    plant may lie beyond the models and the prediction is least sure;
    ``preview_trigger_m`` everywhere when the inner trigger is 0."""
    d = cfg.design
    if d.preview_trigger_inner_m <= 0.0:
        return np.full(len(layer_grid(cfg)), d.preview_trigger_m)
    return np.where(layers_inside_grid(cfg), d.preview_trigger_inner_m, d.preview_trigger_m)


def _clamp_points(cfg: RigConfig, ticks: NDArray[np.int64]) -> int:
    """How many of the checked look-ahead ``ticks`` the stop clamp takes: those within
    ``design.preview_clamp_horizon_s``, at least the first; 0 when the clamp is off."""
    d = cfg.design
    if d.preview_stop_clamp_m <= 0.0:
        return 0
    return max(1, int(np.sum(ticks <= round(d.preview_clamp_horizon_s / cfg.sample_time_s))))


def road_preview(cfg: RigConfig) -> RoadPreview | None:
    """The predictor of ``cfg`` (``design.preview_*``) for every layer of its bank
    (:func:`controller.config.layer_grid`, :func:`controller.config.layer_config`), or
    None when the preview is off (``design.preview_horizon_s`` = 0 or shorter than one
    tick)."""
    d = cfg.design
    dt = cfg.sample_time_s
    horizon = round(d.preview_horizon_s / dt)
    if horizon < 1:
        return None
    step = max(1, round(d.preview_check_s / dt))
    ticks = np.arange(step, horizon + 1, step, dtype=np.int64)
    if ticks.size == 0 or ticks[-1] != horizon:
        ticks = np.append(ticks, np.int64(horizon))
    # with an inner trigger, a layer on the grid's edge keeps the no-force prediction
    force_on = (layers_inside_grid(cfg)[:, None] if d.preview_trigger_inner_m > 0.0
                else np.ones((1, 1), dtype=np.bool_))
    parts = [_layer_predictor(layer_config(cfg, *scales), ticks, horizon)
             for scales in layer_grid(cfg)]
    return RoadPreview(rows=np.ascontiguousarray([p[0] for p in parts]), ticks=ticks,
                       impulse=np.ascontiguousarray([p[1] for p in parts]),
                       force_rows=np.ascontiguousarray([p[2] for p in parts]) * force_on,
                       brake_rows=np.ascontiguousarray([p[3] for p in parts]),
                       horizon_ticks=horizon, trigger_m=layer_triggers_m(cfg),
                       edge_trigger_m=d.preview_trigger_m, clamp_m=d.preview_stop_clamp_m,
                       clamp_points=_clamp_points(cfg, ticks))


_PREDICTORS: dict[str, RoadPreview | None] = {}


def cached_road_preview(cfg: RigConfig) -> RoadPreview | None:
    """:func:`road_preview` of ``cfg`` (0.1-0.2 s for the default bank's 189 layers),
    memoised in this process per hash of the sections it reads
    (:func:`controller.config.design_config_hash`): the runtime's road-at-rest stop
    clamp, the loop's road preview and every simulated run on one configuration share
    one predictor (nothing writes its arrays)."""
    return memoised(_PREDICTORS, design_config_hash(cfg), lambda: road_preview(cfg))


@nb.njit(cache=True, nogil=True, inline="always")
def _fold_peak(peak: float, r: float) -> float:
    """max(peak, |r|), NaN when r is NaN."""
    a = abs(r)
    if a != a:                      # NaN: no prediction
        return math.nan
    return a if a > peak else peak


@nb.njit(cache=True, nogil=True, inline="always")
def _reading_at(rows: np.ndarray, impulse: np.ndarray, layer: int, p: int, j: int,
                dx: np.ndarray, r: float, road_velocity: np.ndarray, start: int,
                nw: int) -> float:
    """The predicted reading at look-ahead tick ``j`` (checked point ``p``) by layer
    ``layer``: ``r`` (the reading's part already summed) plus the state's part, then the
    road's sample by sample from this tick on (``nw`` samples there)."""
    for s in range(4):
        r += rows[layer, p, s] * dx[s]
    for i in range(min(j, nw)):
        r += impulse[layer, j - 1 - i] * road_velocity[start + i]
    return r


#: the stop clamp's window for the RMS error of its own predictions [s]
#: (``design.preview_clamp_trust_m``)
CLAMP_TRUST_WINDOW_S = 0.2


@nb.njit(cache=True, nogil=True)
def clamp_force_bounds_n(rows: np.ndarray, ticks: np.ndarray, impulse: np.ndarray,
                         brake_rows: np.ndarray, layer: int, dx: np.ndarray,
                         reading_m: float, centre_m: float, road_velocity: np.ndarray,
                         start: int, points: int, clamp_m: float,
                         brake_n: float) -> tuple[float, float, float]:
    """The stop clamp's force bounds (``design.preview_stop_clamp_m``): (least force,
    greatest force [N] (> 0 extends, away from the compression stop), the no-force
    prediction at the last look-ahead tick [m]).  The no-force prediction r_p of the LVDT
    reading about the stops' centre (compression positive) at the first ``points`` (at
    least 1) checked look-ahead ticks (:class:`RoadPreview`), by the model of layer
    ``layer`` from the state deviation ``dx`` (4,), the measured reading ``reading_m``
    and the previewed road velocity ``road_velocity[start:]`` [m/s] (fewer samples than a
    look-ahead tick needs: the missing ones count as 0), plus F g_p for a force reference
    F held from the next tick on (``brake_rows``: g_p < 0), stays within ``clamp_m`` at
    every point for F within the bounds: the least force is max_p (r_p - clamp_m) / |g_p|,
    at most ``brake_n``, the
    greatest -max_p (-clamp_m - r_p) / |g_p|, at least -``brake_n`` (-inf / +inf: no
    point bounds it).  Where the no-force prediction reaches a stop the bound asks for
    braking away from it, up to ``brake_n`` (0: refuse to push toward it); elsewhere it
    only limits the push toward the stop.  A NaN prediction gives (0, 0, NaN)."""
    base = reading_m - centre_m
    if base != base:
        return 0.0, 0.0, math.nan
    need_c = -math.inf              # least extension force the compression stop asks
    need_r = -math.inf              # least force toward compression the rebound stop asks
    r = base
    nw = road_velocity.shape[0] - start
    for p in range(min(points, ticks.shape[0])):
        r = _reading_at(rows, impulse, layer, p, ticks[p], dx, base, road_velocity, start,
                        nw)
        if r != r:
            return 0.0, 0.0, math.nan
        g = -brake_rows[layer, p]
        if g > 0.0:
            c = (r - clamp_m) / g
            if c > need_c:
                need_c = c
            c = (-clamp_m - r) / g
            if c > need_r:
                need_r = c
    return min(need_c, brake_n), -min(need_r, brake_n), r


@nb.njit(cache=True, nogil=True)
def predicted_peak_m(rows: np.ndarray, ticks: np.ndarray, impulse: np.ndarray,
                     force_rows: np.ndarray, layer: int, dx: np.ndarray, force_n: float,
                     reading_m: float, centre_m: float, road_velocity: np.ndarray,
                     start: int) -> float:
    """The largest predicted distance of the LVDT reading from the stops' centre [m] over
    the checked look-ahead ticks (:class:`RoadPreview`) by the model of layer ``layer``,
    from the state deviation ``dx`` (4,), the load-cell force ``force_n`` [N] (through
    ``force_rows``; zeros leave it out), the measured reading ``reading_m`` and the
    previewed road velocity [m/s] of this tick and the ones after,
    ``road_velocity[start:]`` (at least ``ticks[-1]`` samples; fewer: the missing ones
    count as 0; no copy is made).  NaN in, NaN out.

    Each look-ahead tick's prediction is summed in one order (the state's part, then the
    road's sample by sample from this tick on); four look-ahead ticks are summed side by
    side over the samples they share, so the four sums do not wait on each other (about
    a third less time than one after the other, the same bits)."""
    base = reading_m - centre_m
    peak = abs(base)
    if peak != peak:
        return math.nan
    nw = road_velocity.shape[0] - start
    n_ticks = ticks.shape[0]
    p = 0
    while p + 4 <= n_ticks:
        j0, j1, j2, j3 = ticks[p], ticks[p + 1], ticks[p + 2], ticks[p + 3]
        a0 = base + force_rows[layer, p] * force_n
        a1 = base + force_rows[layer, p + 1] * force_n
        a2 = base + force_rows[layer, p + 2] * force_n
        a3 = base + force_rows[layer, p + 3] * force_n
        for s in range(4):
            d = dx[s]
            a0 += rows[layer, p, s] * d
            a1 += rows[layer, p + 1, s] * d
            a2 += rows[layer, p + 2, s] * d
            a3 += rows[layer, p + 3, s] * d
        t0, t1, t2, t3 = min(j0, nw), min(j1, nw), min(j2, nw), min(j3, nw)
        for i in range(t0):         # the samples all four share
            v = road_velocity[start + i]
            a0 += impulse[layer, j0 - 1 - i] * v
            a1 += impulse[layer, j1 - 1 - i] * v
            a2 += impulse[layer, j2 - 1 - i] * v
            a3 += impulse[layer, j3 - 1 - i] * v
        for i in range(t0, t1):
            v = road_velocity[start + i]
            a1 += impulse[layer, j1 - 1 - i] * v
            a2 += impulse[layer, j2 - 1 - i] * v
            a3 += impulse[layer, j3 - 1 - i] * v
        for i in range(max(t0, t1), t2):
            v = road_velocity[start + i]
            a2 += impulse[layer, j2 - 1 - i] * v
            a3 += impulse[layer, j3 - 1 - i] * v
        for i in range(max(t0, t1, t2), t3):
            a3 += impulse[layer, j3 - 1 - i] * road_velocity[start + i]
        peak = _fold_peak(_fold_peak(_fold_peak(_fold_peak(peak, a0), a1), a2), a3)
        if peak != peak:
            return math.nan
        p += 4
    while p < n_ticks:              # the last 0-3 look-ahead ticks one by one
        r = _reading_at(rows, impulse, layer, p, ticks[p], dx,
                        base + force_rows[layer, p] * force_n, road_velocity, start, nw)
        peak = _fold_peak(peak, r)
        if peak != peak:
            return math.nan
        p += 1
    return peak
