"""Fuzzy firing weight (thesis App. A): likelihood quotient q -> firing weight in [0, 1].

Input terms SML, MED, LRG, V_LRG are trapezoids [a, b, c, d] on the universe of q
(default (0, 10)); q outside the universe is clamped to it.  Rules: SML -> HIGH,
MED -> MED, LRG -> LOW, V_LRG -> ZERO.  HIGH and ZERO are singletons (at out_high and
out_zero); MED and LOW are triangles.  Inference clips each output set at its rule's
degree (min); defuzzification is the centre of area of the union (max) of the clipped
triangles, with each singleton counted as a point mass of area
(degree x singleton_area) at its location -- a pure area centroid would give singletons
zero weight and ignore the HIGH and ZERO rules entirely (docs/design.md).

The union of clipped triangles is piecewise linear; :func:`fuzzy_inference` integrates
it exactly (area and first moment between all knots and pairwise crossings).
If nothing fires (total mass 0) the weight is 0 and ``FuzzyResult.fired`` is False;
in the tabulated curve such grid points are NaN so the runtime can flag NO_RULE_FIRED.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controller.arrays import FloatArray
from controller.config import FuzzyConfig

__all__ = [
    "FuzzyResult",
    "firing_weight",
    "firing_weight_curve",
    "fuzzy_inference",
    "trapezoid_membership",
]


@dataclass(frozen=True)
class FuzzyResult:
    weight: float          # centre of area in [0, 1]; 0.0 when nothing fired
    mass: float            # total output area incl. singleton point masses
    degrees: tuple[float, float, float, float]  # SML, MED, LRG, V_LRG
    fired: bool


def trapezoid_membership(q: float, t: Sequence[float]) -> float:
    """Degree of q in trapezoid [a, b, c, d] (a == b / c == d are vertical shoulders)."""
    a, b, c, d = (float(v) for v in t)
    if q < a or q > d:
        return 0.0
    if b <= q <= c:
        return 1.0
    if q < b:
        return (q - a) / (b - a)
    return (d - q) / (d - c)



def _clipped_triangle_knots(t: Sequence[float], h: float) -> list[tuple[float, float]]:
    """Knots (x, y) of min(triangle, h) as a piecewise-linear function, zero outside."""
    a, p, c = (float(v) for v in t)
    if h <= 0.0:
        return []
    pts = [(a, 0.0 if p > a else h)]
    if h >= 1.0:
        pts.append((p, 1.0))
    else:
        left = a + h * (p - a)
        right = c - h * (c - p)
        pts.extend([(left, h), (right, h)])
    pts.append((c, 0.0 if c > p else h))
    return pts


def _segments(knots: list[tuple[float, float]]) -> list[tuple[float, float, float, float]]:
    """Non-vertical segments, plus the zero lines outside the support."""
    return [(x0, y0, x1, y1) for (x0, y0), (x1, y1) in itertools.pairwise(knots)
            if x1 > x0]


def _union_area_moment(funcs: list[list[tuple[float, float]]]) -> tuple[float, float]:
    """Exact area and first moment of max(f_i) for piecewise-linear f_i >= 0."""
    funcs = [f for f in funcs if f]
    if not funcs:
        return 0.0, 0.0
    xs = {x for f in funcs for x, _ in f}
    segs = [s for f in funcs for s in _segments(f)]
    for i, (a0, ay0, a1, ay1) in enumerate(segs):  # pairwise crossings
        for b0, by0, b1, by1 in segs[i + 1:]:
            lo, hi = max(a0, b0), min(a1, b1)
            if lo >= hi:
                continue
            sa = (ay1 - ay0) / (a1 - a0)
            sb = (by1 - by0) / (b1 - b0)
            if sa == sb:
                continue
            x = (by0 - sb * b0 - ay0 + sa * a0) / (sa - sb)
            if lo < x < hi:
                xs.add(x)
    grid = sorted(xs)
    area = moment = 0.0
    for x0, x1 in itertools.pairwise(grid):
        h = x1 - x0
        if h <= 0.0:
            continue
        # the max is linear on (x0, x1); evaluate it just inside the ends (vertical
        # shoulders make the union discontinuous only at knots)
        eps = 1e-12 * max(1.0, abs(x0), abs(x1))
        f0 = max(_pl_eval_open(f, x0, +eps) for f in funcs)
        f1 = max(_pl_eval_open(f, x1, -eps) for f in funcs)
        area += 0.5 * (f0 + f1) * h
        moment += h * (f0 * (2.0 * x0 + x1) + f1 * (x0 + 2.0 * x1)) / 6.0
    return area, moment


def _pl_eval_open(knots: list[tuple[float, float]], x: float, side: float) -> float:
    """Limit of the piecewise-linear function at x from the side sign(side)."""
    if not knots:
        return 0.0
    for (x0, y0), (x1, y1) in itertools.pairwise(knots):
        if x1 <= x0:
            continue
        if (side > 0 and x0 <= x < x1) or (side < 0 and x0 < x <= x1):
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return 0.0


def fuzzy_inference(q: float, cfg: FuzzyConfig) -> FuzzyResult:
    """Firing weight of one filter from its likelihood quotient q (App. A)."""
    if math.isnan(q):
        return FuzzyResult(0.0, 0.0, (0.0, 0.0, 0.0, 0.0), False)
    lo, hi = cfg.universe
    qc = min(max(q, lo), hi)
    deg = tuple(trapezoid_membership(qc, t) for t in (cfg.sml, cfg.med, cfg.lrg, cfg.v_lrg))
    d_high, d_med, d_low, d_zero = deg
    area, moment = _union_area_moment([_clipped_triangle_knots(cfg.out_med, d_med),
                                       _clipped_triangle_knots(cfg.out_low, d_low)])
    area += cfg.singleton_area * (d_high + d_zero)
    moment += cfg.singleton_area * (d_high * cfg.out_high + d_zero * cfg.out_zero)
    if area <= 0.0:
        return FuzzyResult(0.0, 0.0, (deg[0], deg[1], deg[2], deg[3]), False)
    w = min(max(moment / area, 0.0), 1.0)
    return FuzzyResult(w, area, (deg[0], deg[1], deg[2], deg[3]), True)


def firing_weight(q: float, cfg: FuzzyConfig) -> float:
    """Centre-of-area firing weight in [0, 1] (0 if nothing fires; see fuzzy_inference)."""
    return fuzzy_inference(q, cfg).weight


def firing_weight_curve(cfg: FuzzyConfig, n: int = 2001) -> tuple[FloatArray, FloatArray]:
    """(q grid over the universe, firing weight) with NaN where no rule fires."""
    if n < 2:
        raise ValueError(f"firing-weight curve needs n >= 2 points, got {n}")
    q = np.linspace(cfg.universe[0], cfg.universe[1], n)
    w = np.empty(n)
    for i, qi in enumerate(q):
        r = fuzzy_inference(float(qi), cfg)
        w[i] = r.weight if r.fired else np.nan
    return q, w
