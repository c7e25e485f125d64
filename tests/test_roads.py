"""Road profiles (hil/sim/roads.py): ISO 8608 RMS and PSD, speed scaling, velocity consistency."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad
from scipy.signal import welch

from hil.sim.roads import (
    ISO_CLASSES,
    ISO_N0,
    ISO_N1,
    ISO_N2,
    ROUGH_COURSE_RMS_M,
    RoadError,
    iso_gd,
    iso_psd,
    iso_rms_m,
    make_road,
)

DT = 1e-3


def test_iso_class_values_are_the_standard_ones() -> None:
    expected = [16, 64, 256, 1024, 4096, 16384, 65536, 262144]
    assert [ISO_CLASSES[c] / 1e-6 for c in "ABCDEFGH"] == pytest.approx(expected)
    # closed-form RMS equals the numerical integral of the PSD over the band
    num, _ = quad(lambda n: float(iso_psd(n, iso_gd("C"))), ISO_N1, ISO_N2, limit=200)
    assert iso_rms_m(iso_gd("C")) == pytest.approx(math.sqrt(num), rel=1e-6)


@pytest.mark.parametrize("cls", list("ABCDEFGH"))
def test_generated_rms_matches_closed_form(cls: str) -> None:
    road = make_road(f"iso-{cls}", 11.176, 100.0, DT, seed=7)
    sigma = math.sqrt(iso_gd(cls) * ISO_N0**2 * (1 / ISO_N1 - 1 / ISO_N2))
    assert road.height_m.std() == pytest.approx(sigma, rel=0.12)
    assert road.roughness_gd == iso_gd(cls)


def test_rms_over_seeds_is_unbiased() -> None:
    rms = [make_road("iso-D", 20.0, 60.0, DT, seed=s).height_m.std() for s in range(8)]
    assert np.mean(np.square(rms)) == pytest.approx(iso_rms_m(iso_gd("D")) ** 2, rel=0.1)


def _band_ratios(road, speed: float, gd: float) -> np.ndarray:
    """Welch PSD / spec, averaged over octave bands inside the sampled band."""
    f, p = welch(road.height_m, fs=1 / DT, nperseg=2**15)
    spec = iso_psd(f / speed, gd) / speed        # temporal one-sided PSD [m^2/Hz]
    lo, hi = max(ISO_N1 * speed * 4, 0.2), min(ISO_N2 * speed * 0.8, 60.0)
    edges = lo * 2.0 ** np.arange(0, math.log2(hi / lo))
    ratios = []
    for a, b in itertools.pairwise(edges):
        m = (f >= a) & (f < b)
        ratios.append(p[m].sum() / spec[m].sum())
    return np.array(ratios)


@pytest.mark.parametrize("speed", [8.0, 25.0])
def test_psd_follows_iso_spectrum_at_the_vehicle_speed(speed: float) -> None:
    """G(f) = Gd(f / V) / V: generated spatially, so a speed change moves the spectrum."""
    road = make_road("iso-C", speed, 250.0, DT, seed=3)
    r = _band_ratios(road, speed, iso_gd("C"))
    assert len(r) >= 3
    assert np.all(np.abs(r - 1.0) < 0.3), r


def test_rough_course_is_135_inch_rms() -> None:
    road = make_road("rough-course", 11.176, 120.0, DT, seed=1)
    assert pytest.approx(0.03429) == ROUGH_COURSE_RMS_M
    assert road.height_m.std() == pytest.approx(ROUGH_COURSE_RMS_M, rel=0.12)
    assert road.roughness_gd is not None
    assert iso_rms_m(road.roughness_gd) == pytest.approx(ROUGH_COURSE_RMS_M, rel=1e-12)


@settings(max_examples=10, deadline=None)
@given(name=st.sampled_from(["iso-B", "rough-course", "datp", "bump", "pothole", "sweep"]),
       speed=st.floats(2.0, 30.0), seed=st.integers(0, 2**31))
def test_velocity_integrates_to_height(name: str, speed: float, seed: int) -> None:
    road = make_road(name, speed, 3.0, DT, seed=seed)
    assert road.height_m[0] == 0.0
    h = np.concatenate([[0.0], np.cumsum(road.velocity_mps) * DT])
    np.testing.assert_allclose(h[:-1], road.height_m, atol=1e-9)
    assert np.all(np.isfinite(road.velocity_mps))


def test_same_seed_same_road_different_seed_different_road() -> None:
    a = make_road("iso-C", 10.0, 5.0, DT, seed=1).height_m
    b = make_road("iso-C", 10.0, 5.0, DT, seed=1).height_m
    c = make_road("iso-C", 10.0, 5.0, DT, seed=2).height_m
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_discrete_events() -> None:
    bump = make_road("bump", 10.0, 2.0, DT)
    assert bump.height_m.max() == pytest.approx(0.08, rel=1e-3)
    assert bump.height_m[: int(0.49 / DT)].max() == 0.0        # starts at 5 m
    pot = make_road("pothole", 10.0, 2.0, DT)
    assert pot.height_m.min() == pytest.approx(-0.06, rel=1e-6)
    sweep = make_road("sweep", 10.0, 20.0, DT)
    assert np.abs(sweep.velocity_mps).max() == pytest.approx(0.1, rel=0.05)
    datp = make_road("datp", 10.0, 20.0, DT, seed=4)
    assert datp.height_m.max() - np.median(datp.height_m) > 0.03


def test_csv_profile(tmp_path: Path) -> None:
    p = tmp_path / "course.csv"
    x = np.linspace(0, 100, 1001)
    p.write_text("distance_m,height_m\n" + "\n".join(f"{a},{0.01 * a}" for a in x))
    road = make_road(f"csv:{p}", 5.0, 2.0, DT)
    assert road.velocity_mps == pytest.approx(np.full(2000, 0.05), abs=1e-9)
    with pytest.raises(RoadError, match="covers"):
        make_road(f"csv:{p}", 50.0, 10.0, DT)


@pytest.mark.parametrize(("name", "match"), [
    ("iso-Z", "ISO 8608 class"), ("gravel", "unknown road"), ("csv:/nonexistent.csv",
                                                                "not readable"),
])
def test_bad_names_give_clear_errors(name: str, match: str) -> None:
    with pytest.raises(RoadError, match=match):
        make_road(name, 10.0, 1.0, DT)


def test_bad_csv_and_arguments(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("0,0\n1,0\n0.5,1\n")
    with pytest.raises(RoadError, match="line 3: distance must be strictly increasing"):
        make_road(f"csv:{p}", 1.0, 2.0, DT)
    make_road(f"csv:{p}", 1.0, 0.1, DT)     # a run of 0.1 m reads the first two rows
    p.write_text("0,0\n1,abc\n")
    with pytest.raises(RoadError, match="line 2"):
        make_road(f"csv:{p}", 1.0, 0.1, DT)
    with pytest.raises(RoadError, match="speed_mps"):
        make_road("iso-A", -1.0, 1.0, DT)
    with pytest.raises(RoadError, match="duration_s"):
        make_road("iso-A", 1.0, math.nan, DT)


def test_check_road_accepts_what_make_road_builds(tmp_path: Path) -> None:
    from hil.sim.roads import ROAD_NAMES, check_road

    for name in ROAD_NAMES:
        if name != "csv:PATH":
            assert check_road(name) == name
            make_road(name, 10.0, 0.1, 1e-3)
    csv = tmp_path / "p.csv"
    csv.write_text("0,0\n100,0.01\n")
    assert check_road(f"csv:{csv}") == f"csv:{csv}"
    for bad, match in (("iso-Z", "ISO 8608 class"), ("gravel", "unknown road"),
                       (f"csv:{tmp_path / 'none.csv'}", "not readable"),
                       (f"csv:{tmp_path}", "not readable")):
        with pytest.raises(RoadError, match=match):
            check_road(bad)
