"""Fuzzy firing weight (App. A) against an independent dense-grid centre of area."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import FuzzyConfig, default_config
from controller.fuzzy import (
    firing_weight,
    firing_weight_curve,
    fuzzy_inference,
    trapezoid_membership,
)

FZ = default_config().fuzzy
XS = np.linspace(0.0, 1.0, 200_001)


def _trap(q: float, t: list[float]) -> float:
    a, b, c, d = t
    left = 1.0 if b == a else np.clip((q - a) / (b - a), 0.0, 1.0)
    right = 1.0 if d == c else np.clip((d - q) / (d - c), 0.0, 1.0)
    inside = a <= q <= d
    return float(min(left, right)) if inside else 0.0


def _tri(x: np.ndarray, t: list[float]) -> np.ndarray:
    a, p, c = t
    with np.errstate(over="ignore"):   # a ramp a few ulps wide: inf, clipped to 1 below
        up = np.ones_like(x) if p == a else (x - a) / (p - a)
        down = np.ones_like(x) if c == p else (c - x) / (c - p)
    return np.clip(np.minimum(up, down), 0.0, 1.0) * ((x >= a) & (x <= c))


def reference_weight(q: float, fz: FuzzyConfig) -> tuple[float, float]:
    """Dense-grid max-union of the clipped triangles + singleton point masses."""
    qc = min(max(q, fz.universe[0]), fz.universe[1])
    d_high, d_med, d_low, d_zero = (_trap(qc, t) for t in (fz.sml, fz.med, fz.lrg, fz.v_lrg))
    mu = np.maximum(np.minimum(_tri(XS, fz.out_med), d_med),
                    np.minimum(_tri(XS, fz.out_low), d_low))
    area = float(np.trapezoid(mu, XS))
    moment = float(np.trapezoid(mu * XS, XS))
    area += fz.singleton_area * (d_high + d_zero)
    moment += fz.singleton_area * (d_high * fz.out_high + d_zero * fz.out_zero)
    return (moment / area if area > 0 else 0.0), area


@pytest.mark.parametrize("q", [*np.linspace(-1.0, 11.0, 61).tolist(), 2.345, 4.9, 5.5, 7.77])
def test_weight_matches_dense_grid_centroid(q: float) -> None:
    ref, mass = reference_weight(q, FZ)
    r = fuzzy_inference(q, FZ)
    assert r.weight == pytest.approx(ref, abs=2e-6)
    assert r.mass == pytest.approx(mass, abs=2e-6)


def test_closed_form_values() -> None:
    # q = 2: HIGH 0.5 (mass 0.125 at 1), MED clipped at 0.5 (area 0.1875 at 0.5) -> 0.7
    assert firing_weight(2.0, FZ) == pytest.approx(0.7, abs=1e-14)
    assert firing_weight(3.5, FZ) == pytest.approx(0.5, abs=1e-14)
    assert firing_weight(5.0, FZ) == pytest.approx(0.375, abs=1e-14)
    assert firing_weight(6.5, FZ) == pytest.approx(0.25, abs=1e-14)
    assert firing_weight(8.0, FZ) == pytest.approx(0.15, abs=1e-14)
    assert firing_weight(0.0, FZ) == 1.0
    assert firing_weight(10.0, FZ) == 0.0
    assert firing_weight(1e9, FZ) == 0.0       # clamped to the universe
    assert firing_weight(-5.0, FZ) == 1.0


def test_singletons_are_not_ignored() -> None:
    """A pure area centroid would give 0.5 at q = 2 (only MED has area); ours is 0.7."""
    assert firing_weight(2.0, FZ) > 0.5
    bigger = FZ.__class__(**{**FZ.__dict__, "singleton_area": 0.5})
    assert firing_weight(2.0, bigger) > firing_weight(2.0, FZ)


def test_curve_monotone_non_increasing_and_matches_pointwise() -> None:
    q, w = firing_weight_curve(FZ, 2001)
    assert q[0] == FZ.universe[0] and q[-1] == FZ.universe[1]
    assert np.all(np.isfinite(w))
    assert np.all(np.diff(w) <= 1e-15)
    for i in range(0, 2001, 97):
        assert w[i] == firing_weight(float(q[i]), FZ)


def test_no_rule_fired_is_detectable() -> None:
    gap = FZ.__class__(**{**FZ.__dict__, "sml": [0.0, 0.0, 1.0, 2.0],
                          "med": [3.0, 4.0, 5.0, 6.0]})
    r = fuzzy_inference(2.5, gap)
    assert not r.fired and r.weight == 0.0 and r.mass == 0.0
    q, w = firing_weight_curve(gap, 1001)
    assert np.isnan(w[np.argmin(np.abs(q - 2.5))])
    assert not fuzzy_inference(float("nan"), FZ).fired
    with pytest.raises(ValueError):
        firing_weight_curve(FZ, 1)


def test_trapezoid_shoulders() -> None:
    assert trapezoid_membership(0.0, [0.0, 0.0, 1.0, 3.0]) == 1.0
    assert trapezoid_membership(10.0, [7.0, 9.0, 10.0, 10.0]) == 1.0
    assert trapezoid_membership(2.0, [0.0, 0.0, 1.0, 3.0]) == pytest.approx(0.5)


@settings(max_examples=200, deadline=None)
@given(q=st.floats(allow_nan=False, allow_infinity=True))
def test_weight_in_unit_interval(q: float) -> None:
    w = firing_weight(q, FZ)
    assert 0.0 <= w <= 1.0


def _sorted4(xs: list[float]) -> list[float]:
    return sorted(xs)


@settings(max_examples=60, deadline=None)
@given(
    sets=st.lists(st.lists(st.floats(0.0, 10.0), min_size=4, max_size=4).map(_sorted4),
                  min_size=4, max_size=4),
    med=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3).map(sorted),
    low=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3).map(sorted),
    area=st.floats(0.01, 1.0),
    q=st.floats(-1.0, 11.0),
)
def test_random_configs_agree_with_reference(sets: list[list[float]], med: list[float],
                                             low: list[float], area: float, q: float) -> None:
    if med[2] - med[0] < 1e-3 or low[2] - low[0] < 1e-3:
        return
    fz = FZ.__class__(**{**FZ.__dict__, "sml": sets[0], "med": sets[1], "lrg": sets[2],
                         "v_lrg": sets[3], "out_med": med, "out_low": low,
                         "singleton_area": area})
    r = fuzzy_inference(q, fz)
    assert 0.0 <= r.weight <= 1.0
    ref, mass = reference_weight(q, fz)
    if mass > 1e-3:
        # dense grid error grows near vertical edges of very narrow sets
        assert r.weight == pytest.approx(ref, abs=1e-4)
    assert math.isfinite(r.mass)
