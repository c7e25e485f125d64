"""Layers of the bank (issue 22, docs/design.md §11): the scheduler that runs the layer
nearest the estimate of sprung mass, spring rate and damping.

The design holds the tire models once per layer (``design.sprung_mass_scales`` x
``spring_rate_scales`` x ``damping_scales``, :func:`controller.config.layer_scales`;
layer major: model j of layer l is ``l * NTIRE + t``, the airborne model last).  The bank
runs one layer at a time: fuzzy and Bayes blend that layer's tire models (and the airborne
model), the single LQG is that layer's counterpart of the configured single model, the
moving bank walks within the layer.  :func:`mass_schedule` moves to the layer nearest the
estimate (the sum of |log ratio| over the axes with more than one value) once that layer
has been nearer than the current one by more than the hysteresis ``F_LHYST`` for
``I_LDWELL`` ticks in a row (the estimate dips for a few tenths of a second just after a
ballast change: the weight the spring does not carry yet passes the band-pass as a
transient; while the estimator holds after an isolated stop contact the estimate is no
news, and the count waits); the newcomers start bumpless from the blended deviation and biases
(:func:`controller.runtime.kernels.activate`), as the moving bank's do.

Where the LVDT reads 0: each model reads the rattlespace about its own static position
(the reading + M_l g / K_l - M g / K, ``V_YSTAT``: its own static deflection less the
configured rig's), right for a rig whose LVDT reads 0 at rest with the ballast and spring
it has (zeroed there, or the ride height set by preload); after a ballast change without
re-zeroing the LVDT's sag of ΔM g / K is an offset to the heavier layer's models, which
their rattlespace-bias state takes up (as it is for the single-layer bank).

A candidate layer's filters (the counterparts of the running ones; not in the moving
bank, whose supervisor re-centres onto any running filter) are warmed up while the
candidate waits out its dwell: they run without contributing to the force, the
monitor or the probabilities, so at the change they are settled (started cold at the
change, the new filters' q put the bank into DEGRADED for 0.6 s on the 0.7 x plant).

:func:`layer_table` takes the layers from the design's own configuration and checks them
against the models' equilibria (the static deflection M g / K of each model), so the
artifact needs no field of its own.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from controller.arrays import FloatArray
from controller.mass_estimator import ME_HOLD
from controller.runtime import kernels as kern
from controller.runtime.moving_bank import enter_moving

__all__ = ["gather_running_layer", "layer_table", "mass_schedule", "model_in_layer",
           "running_layer_rows"]

_MOVING = int(kern.Blending.MOVING)


def layer_table(equilibrium: FloatArray, airborne: NDArray[np.bool_], layers: FloatArray,
                gravity_mps2: float) -> tuple[FloatArray, NDArray[np.int64], int]:
    """(``layers``, layer of each model (-1 airborne), on-ground models per layer) for a
    design whose layers are ``layers`` (L, 3): sprung mass [kg], spring rate [N/m] and
    damping [N s/m] of each, in the bank's order (:func:`controller.config.layer_scales`
    x the configured vehicle).  ValueError unless the on-ground models are layer major
    with the same number per layer and each model's static suspension deflection
    (equilibrium) is its layer's M g / K."""
    layers = np.asarray(layers, dtype=float).reshape(-1, 3)
    ground = np.flatnonzero(~airborne)
    layer = -np.ones(airborne.shape[0], dtype=np.int64)
    n_layers = layers.shape[0]
    if ground.size == 0 or ground.size % n_layers or \
            not np.array_equal(ground, np.arange(ground.size)):
        raise ValueError(f"the design's models are not {n_layers} layers of one tire family "
                         "each, layer major (controller.design.design_models)")
    n_tire = ground.size // n_layers
    layer[ground] = ground // n_tire
    if gravity_mps2 > 0.0:
        sag = equilibrium[ground, 0] - equilibrium[ground, 1]
        want = layers[layer[ground], 0] * gravity_mps2 / layers[layer[ground], 1]
        if not np.allclose(sag, want, rtol=1e-6, atol=1e-9):
            raise ValueError("the design's models are not those of its configured layers "
                             "(static deflection != M g / K of the layer)")
    return layers, layer, n_tire


def running_layer_rows(n_models: int, n_layers: int, n_tire: int, layer: int
                       ) -> NDArray[np.int64]:
    """The bank's model indices of ``layer``'s models, in the order the tick record's
    columns have them (docs/recording.md): its ``n_tire`` on-ground models, then the
    airborne models the layers share.  For a one-layer bank: every model, in order."""
    ground = layer * n_tire + np.arange(n_tire, dtype=np.int64)
    return np.concatenate([ground, np.arange(n_layers * n_tire, n_models, dtype=np.int64)])


@nb.njit(cache=True, nogil=True)
def gather_running_layer(st: np.ndarray, active: np.ndarray, iv: np.ndarray,
                         st_out: np.ndarray, active_out: np.ndarray,
                         models_out: np.ndarray) -> None:
    """Copy the running layer's rows of the state ``st`` and ``active`` into ``st_out`` /
    ``active_out`` and their bank indices into ``models_out`` (the rows of
    :func:`running_layer_rows` for ``iv[I_LAYER]``).  Allocation-free."""
    n = iv[kern.I_NTIRE]
    base = iv[kern.I_LAYER] * n
    air = n * iv[kern.I_NLAYER]
    for k in range(st_out.shape[0]):
        j = base + k if k < n else air + k - n
        models_out[k] = j
        active_out[k] = active[j]
        for c in range(st.shape[1]):
            st_out[k, c] = st[j, c]


@nb.njit(cache=True, nogil=True, inline="always")
def model_in_layer(j: int, layer: int, iv: np.ndarray) -> int:
    """Model j's counterpart (same tire model) in ``layer``; the airborne model is its own."""
    n = iv[kern.I_NTIRE]
    if j >= n * iv[kern.I_NLAYER]:
        return j
    return layer * n + j % n


@nb.njit(cache=True, nogil=True, inline="always")
def _warm(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
          mat: np.ndarray, layer: int, on: bool) -> None:
    """Start (``on``) or stop the filters of ``layer`` that are the counterparts of the
    running layer's running filters: they run without contributing until the layer
    change (bumpless start from the blended deviation and biases)."""
    n = iv[kern.I_NTIRE]
    cur = iv[kern.I_LAYER]
    for t in range(n):
        if active[cur * n + t]:
            j = layer * n + t
            if on and not active[j]:
                kern.activate(j, st, active, fv, iv, mat, kern.QS_INIT, 0.0)
            elif not on and active[j]:
                kern.deactivate(j, st, active, iv)


@nb.njit(cache=True, nogil=True, inline="always")
def _layer_distance(vec: np.ndarray, j: int, fv: np.ndarray, log_m: float, log_k: float,
                    log_c: float, log_f: float) -> float:
    """Distance of the estimate (logs of [M, K, C] and of the passive wheel-hop
    frequency) from model j's layer: the sum of |log ratio| over the axes on which the
    bank has more than one layer (``F_LWK`` / ``F_LWC`` 0 or 1 for spring rate and
    damping; mass always).  Tire layers (``F_LWT`` > 0) count the wheel hop against the
    layer's own predicted one, |log ratio| x ``F_LWT`` (in units of log tire
    stiffness), or, while there is no estimate (``log_f`` NaN), the layer's tire against
    the configured one."""
    p = kern.V_LOGP
    d = abs(log_m - vec[j, p])
    if fv[kern.F_LWK] > 0.0:
        d += abs(log_k - vec[j, p + 1])
    if fv[kern.F_LWC] > 0.0:
        d += abs(log_c - vec[j, p + 2])
    if fv[kern.F_LWT] > 0.0:
        if math.isnan(log_f):
            d += abs(vec[j, p + 3])
        else:
            d += abs(log_f - vec[j, p + 4]) * fv[kern.F_LWT]
    return d


@nb.njit(cache=True, nogil=True)
def mass_schedule(st: np.ndarray, active: np.ndarray, fv: np.ndarray, iv: np.ndarray,
                  nbr: np.ndarray, vec: np.ndarray, mat: np.ndarray, mass_est_kg: float,
                  spring_est_n_per_m: float, damping_est_ns_per_m: float,
                  wheel_hop_hz: float, blend: int) -> None:
    """Move the bank to the layer nearest the estimate of [M, K, C] and of the passive
    wheel-hop frequency ``wheel_hop_hz`` (NaN: the rig has not been seen passive; the
    configured tire's layers then; see the module docstring)."""
    nl = iv[kern.I_NLAYER]
    if nl <= 1:
        return
    if not (mass_est_kg > 0.0 and spring_est_n_per_m > 0.0 and damping_est_ns_per_m > 0.0):
        return
    if fv[kern.F_MES + ME_HOLD] > 0.0:
        return      # the estimator holds (an isolated stop contact): no news, the dwell waits
    log_m = math.log(mass_est_kg)
    log_k = math.log(spring_est_n_per_m)
    log_c = math.log(damping_est_ns_per_m)
    # (only a bank with tire layers reads it; NaN compares False)
    log_f = math.log(wheel_hop_hz) if fv[kern.F_LWT] > 0.0 and wheel_hop_hz > 0.0 else np.nan
    n = iv[kern.I_NTIRE]
    cur = iv[kern.I_LAYER]
    d_cur = _layer_distance(vec, cur * n, fv, log_m, log_k, log_c, log_f)
    best = cur
    d_best = d_cur
    for lay in range(nl):
        d = _layer_distance(vec, lay * n, fv, log_m, log_k, log_c, log_f)
        if d < d_best:
            best = lay
            d_best = d
    cand = iv[kern.I_LCAND]
    if best == cur or d_best + fv[kern.F_LHYST] >= d_cur:
        if cand >= 0:                   # no candidate any more: stop warming it
            _warm(st, active, fv, iv, mat, cand, False)
            iv[kern.I_LCAND] = -1
        iv[kern.I_LSINCE] = 0
        return
    if best != cand:                    # a new candidate: warm its filters up
        if cand >= 0:
            _warm(st, active, fv, iv, mat, cand, False)
        iv[kern.I_LCAND] = best
        iv[kern.I_LSINCE] = 0
        if blend != _MOVING:            # (the moving bank would re-centre onto them)
            _warm(st, active, fv, iv, mat, best, True)
    iv[kern.I_LSINCE] += 1
    if iv[kern.I_LSINCE] < iv[kern.I_LDWELL]:
        return                          # not preferred long enough yet
    if blend == _MOVING and iv[kern.I_MODE] == kern.MODE_AIR:
        return                          # change layers on the ground
    # the change: the warm filters take over, the old layer's stop
    iv[kern.I_LAYER] = best
    iv[kern.I_LCAND] = -1
    iv[kern.I_LSINCE] = 0
    iv[kern.I_NLAYERSW] += 1
    iv[kern.I_SINGLE] = model_in_layer(iv[kern.I_SINGLE0], best, iv)
    if blend == _MOVING:
        centre = model_in_layer(iv[kern.I_CENTRE], best, iv)
        for j in range(n * nl):
            if active[j] and j // n != best:
                kern.deactivate(j, st, active, iv)
        enter_moving(st, active, fv, iv, nbr, vec, mat, centre)
        return
    k = 0
    for t in range(n):
        if active[cur * n + t]:
            k += 1
    for t in range(n):
        old = cur * n + t
        new = best * n + t
        if active[old]:
            p = st[old, kern.S_P]
            kern.deactivate(old, st, active, iv)
            if not active[new]:         # (not warmed: e.g. the set changed meanwhile)
                kern.activate(new, st, active, fv, iv, mat, kern.QS_INIT, 0.0)
            st[new, kern.S_P] = p if p > 0.0 else 1.0 / k
    kern.normalise_probabilities(st, iv)
