"""Road profiles for the emulated rig, generated on the distance axis and sampled in time.

``make_road(name, speed_mps, duration_s, dt_s, seed)`` returns a :class:`Road` whose
``height_m[k]`` is the road height under the tire at t_k = k dt and ``velocity_mps[k]``
= (h(t_{k+1}) - h(t_k)) / dt, the exact mean road velocity over tick k, so integrating
the held velocity reproduces the profile at every tick (``RigPlant.advance``).

Names:

``iso-A`` .. ``iso-H``
    ISO 8608 random roads: Gd(n) = Gd(n0) (n / n0)^-2, n0 = 0.1 cycle/m,
    Gd(n0) = 16 x 4^k e-6 m^3 (k = 0 for A .. 7 for H), band 0.011 - 2.83 cycle/m.
    Generated spatially as a sum of sinusoids on an FFT grid (random phases, bin power
    equal to the exact integral of Gd over the bin), so the variance is the closed form
    sigma^2 = Gd(n0) n0^2 (1/n1 - 1/n2) and a speed change moves the temporal spectrum
    (G(f) = Gd(f / V) / V).
``rough-course``
    Stand-in for the thesis's 1.35 in RMS Letourneau course: the ISO shape scaled to
    1.35 in (34.29 mm) RMS over the band (Gd(n0) = 1.30e-3 m^3, between classes D and E).
``datp``
    Bumpy DAT-P-like course: class-C roughness plus rounded bumps 40-100 mm high,
    0.5-1.5 m long, 4-12 m apart (random, from the seed).
``bump`` / ``pothole``
    One 1-cos bump 80 mm high and 1 m long / one 60 mm deep, 0.6 m long pothole with
    steep (50 mm) cosine edges, 5 m after the start.
``sweep``
    Logarithmic sine sweep 0.5 -> 25 Hz over the run with a constant 0.1 m/s road
    velocity amplitude (height amplitude 0.1 / (2 pi f)); ``speed_mps`` only scales the
    spatial wavelength.
``flat``
    The road held at rest (height and velocity 0): the shaker of an identification run
    (``rig demo --excite``, ``rig hil --excite``).
``csv:PATH``
    Measured profile: two columns distance [m], height [m] (comma separated, optional
    header line, UTF-8 with or without a byte order mark), distance strictly
    increasing, heights within +/- :data:`MAX_ROAD_HEIGHT_M`; linear interpolation.  At
    most :data:`MAX_CSV_BYTES` (a 100 km profile at 1 cm spacing); a run reads the rows
    it needs (up to its distance) and stops, so an error further on is not seen.

``check_road(name)`` validates a name (and reads a ``csv:`` file) without building the
road: the command line checks ``--road`` with it before anything else runs.
"""

from __future__ import annotations

import io
import math
import os
from array import array
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from controller.arrays import FloatArray
from controller.files import NotRegularFileError, open_regular

__all__ = [
    "ISO_CLASSES",
    "ISO_N0",
    "ISO_N1",
    "ISO_N2",
    "MAX_CSV_BYTES",
    "MAX_ROAD_HEIGHT_M",
    "ROAD_NAMES",
    "ROUGH_COURSE_RMS_M",
    "Road",
    "RoadError",
    "check_road",
    "iso_gd",
    "iso_psd",
    "iso_rms_m",
    "iso_spatial_profile",
    "make_road",
]


ISO_N0 = 0.1     # cycle/m
ISO_N1 = 0.011   # cycle/m, lower band edge
ISO_N2 = 2.83    # cycle/m, upper band edge
#: Gd(n0) [m^3] per ISO 8608 class (geometric mean of each class).
ISO_CLASSES: dict[str, float] = {c: 16e-6 * 4.0**k for k, c in enumerate("ABCDEFGH")}
ROUGH_COURSE_RMS_M = 1.35 * 0.0254
ROAD_NAMES = (*[f"iso-{c}" for c in ISO_CLASSES], "rough-course", "datp", "bump",
              "pothole", "sweep", "flat", "csv:PATH")
#: largest ``csv:`` profile file (a run reads only the rows it needs)
MAX_CSV_BYTES = 256 << 20
#: largest height of a ``csv:`` profile: a road under a quarter car, not a survey of
#: altitudes (a profile's height is the tire's base input; 1e300 would overflow)
MAX_ROAD_HEIGHT_M = 10.0


class RoadError(ValueError):
    """Unknown road name, bad arguments or an unreadable/invalid profile file."""


@dataclass(frozen=True)
class Road:
    """A road sampled at the controller tick.  Arrays have one entry per tick."""

    name: str
    speed_mps: float
    dt_s: float
    height_m: FloatArray
    velocity_mps: FloatArray
    roughness_gd: float | None = None   # Gd(n0) [m^3] for the noise table, if known
    description: str = ""
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def n_ticks(self) -> int:
        return int(self.height_m.shape[0])

    @property
    def duration_s(self) -> float:
        return self.n_ticks * self.dt_s

    @property
    def time_s(self) -> FloatArray:
        return np.arange(self.n_ticks, dtype=np.float64) * self.dt_s


def iso_gd(road_class: str) -> float:
    """Gd(n0) [m^3] of an ISO 8608 class letter A..H."""
    try:
        return ISO_CLASSES[road_class.upper()]
    except KeyError:
        raise RoadError(f"unknown ISO 8608 class {road_class!r}: use one of "
                        f"{', '.join(ISO_CLASSES)}") from None


def iso_psd(n_cpm: FloatArray | float, gd_n0: float) -> FloatArray:
    """One-sided displacement PSD Gd(n) [m^3] inside the band, 0 outside."""
    n = np.asarray(n_cpm, dtype=float)
    with np.errstate(divide="ignore"):
        g = gd_n0 * (np.where(n > 0, n, np.inf) / ISO_N0) ** -2.0
    return np.asarray(np.where((n >= ISO_N1) & (n <= ISO_N2), g, 0.0), dtype=np.float64)


def iso_rms_m(gd_n0: float, n1: float = ISO_N1, n2: float = ISO_N2) -> float:
    """Closed-form RMS height over [n1, n2]: sqrt(Gd(n0) n0^2 (1/n1 - 1/n2))."""
    return math.sqrt(gd_n0 * ISO_N0**2 * (1.0 / n1 - 1.0 / n2))


def iso_spatial_profile(gd_n0: float, length_m: float, dx_m: float,
                        rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """(distance [m], height [m]) of an ISO-shaped random profile at spacing ``dx_m``.

    FFT grid of period >= max(length, 4 / n1); each bin's amplitude a_i carries the exact
    integral of Gd over the bin clipped to the band (a_i^2 / 2 = int Gd dn), random phase.
    """
    if not (0.0 < dx_m <= 0.5 / ISO_N2):
        raise RoadError(f"profile spacing {dx_m} m must be in (0, {0.5 / ISO_N2:.3f}] m")
    period = max(length_m, 4.0 / ISO_N1)
    n_pts = 1 << math.ceil(math.log2(period / dx_m + 1))
    dn = 1.0 / (n_pts * dx_m)
    k = np.arange(n_pts // 2 + 1)
    lo = np.clip((k - 0.5) * dn, ISO_N1, ISO_N2)
    hi = np.clip((k + 0.5) * dn, ISO_N1, ISO_N2)
    power = np.zeros_like(lo)
    ok = hi > lo
    power[ok] = gd_n0 * ISO_N0**2 * (1.0 / lo[ok] - 1.0 / hi[ok])
    amp = np.sqrt(2.0 * power)
    phase = rng.uniform(0.0, 2.0 * math.pi, size=k.shape)
    spec = amp * np.exp(1j * phase) * (n_pts / 2.0)
    spec[0] = 0.0
    h = np.fft.irfft(spec, n=n_pts)
    x = np.arange(n_pts, dtype=np.float64) * dx_m
    return x, np.asarray(h, dtype=np.float64)


def _sample(distance: FloatArray, height: FloatArray, speed: float, n_ticks: int,
            dt: float) -> FloatArray:
    s = np.arange(n_ticks + 1) * dt * speed
    return np.interp(s, distance, height)


def _finish(name: str, speed: float, dt: float, h_edges: FloatArray, gd: float | None,
            description: str, **extra: float) -> Road:
    h_edges = h_edges - h_edges[0]
    vel = np.diff(h_edges) / dt
    return Road(name, speed, dt, np.ascontiguousarray(h_edges[:-1]),
                np.ascontiguousarray(vel), gd, description, dict(extra))


def _cosine_bump(s: FloatArray, start: float, length: float, height: float) -> FloatArray:
    u = (s - start) / length
    inside = (u >= 0) & (u <= 1)
    return np.where(inside, 0.5 * height * (1.0 - np.cos(2.0 * math.pi * u)), 0.0)


def _pothole(s: FloatArray, start: float, length: float, depth: float,
             edge: float) -> FloatArray:
    """Flat-bottomed dip with cosine edges of length ``edge``."""
    d = np.zeros_like(s)
    a, b = start, start + length
    down = (s >= a) & (s < a + edge)
    d[down] = 0.5 * (1 - np.cos(math.pi * (s[down] - a) / edge))
    d[(s >= a + edge) & (s <= b - edge)] = 1.0
    up = (s > b - edge) & (s <= b)
    d[up] = 0.5 * (1 - np.cos(math.pi * (b - s[up]) / edge))
    return -depth * d


def _read_csv(path: str, need_m: float | None = None) -> tuple[FloatArray, FloatArray]:
    """(distance, height) of a ``csv:`` profile, read line by line and checked as it is
    read; ``need_m``: stop at the first row ``need_m`` metres or more past the first (a
    run reads what it needs of a long profile, not the whole file; None: read it all)."""
    p = Path(path)
    try:
        f = open_regular(p)
    except NotRegularFileError as exc:
        raise RoadError(f"road file {path!r} is not readable: it {exc.what}") from None
    except OSError as exc:
        raise RoadError(f"road file {path!r} is not readable: {exc}") from exc
    with f:
        if os.fstat(f.fileno()).st_size > MAX_CSV_BYTES:
            raise RoadError(f"road file {path!r} is larger than {MAX_CSV_BYTES} bytes")
        # utf-8-sig: a byte order mark (spreadsheet export) is not part of the first row
        text = io.TextIOWrapper(f, encoding="utf-8-sig", newline=None)
        try:
            dist, height = _profile_rows(path, text, need_m)
        except (OSError, UnicodeDecodeError) as exc:
            raise RoadError(f"road file {path!r} is not readable: {exc}") from exc
    if len(dist) < 2:
        raise RoadError(f"road file {path!r}: needs at least two 'distance,height' rows")
    return np.frombuffer(dist, dtype=np.float64), np.frombuffer(height, dtype=np.float64)


def _profile_rows(path: str, lines: Iterable[str], need_m: float | None
                  ) -> tuple[array[float], array[float]]:
    dist: array[float] = array("d")
    height: array[float] = array("d")
    for i, raw in enumerate(lines, 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(",")
        try:
            if len(parts) != 2:
                raise ValueError
            d, h = float(parts[0]), float(parts[1])
        except ValueError:
            if not dist and i == 1:
                continue    # header line
            raise RoadError(f"road file {path!r} line {i}: expected 'distance_m,height_m', "
                            f"got {line[:80]!r}") from None
        if not (math.isfinite(d) and math.isfinite(h)):
            raise RoadError(f"road file {path!r} line {i}: non-finite values")
        if abs(h) > MAX_ROAD_HEIGHT_M:
            raise RoadError(f"road file {path!r} line {i}: height {h:g} m is not a "
                            f"physical road height; allowed [-{MAX_ROAD_HEIGHT_M:g}, "
                            f"{MAX_ROAD_HEIGHT_M:g}] m")
        if dist and d <= dist[-1]:
            raise RoadError(f"road file {path!r} line {i}: distance must be strictly "
                            f"increasing ({d:g} after {dist[-1]:g})")
        dist.append(d)
        height.append(h)
        if need_m is not None and len(dist) >= 2 and d - dist[0] >= need_m:
            break
    return dist, height


_FIXED_ROADS = ("rough-course", "datp", "bump", "pothole", "sweep", "flat")


def check_road(name: str) -> str:
    """``name`` if :func:`make_road` knows it (a ``csv:`` file must read as a profile;
    whether it is long enough depends on the run); :class:`RoadError` naming the problem
    otherwise."""
    key = name.strip()
    low = key.lower()
    if low.startswith("iso-") and len(low) == 5:
        iso_gd(low[4])
    elif key.startswith("csv:"):
        _read_csv(key[4:], need_m=0.0)      # readable, first rows valid
    elif low not in _FIXED_ROADS:
        raise RoadError(f"unknown road {name!r}: use one of {', '.join(ROAD_NAMES)}")
    return name


def make_road(name: str, speed_mps: float, duration_s: float, dt_s: float,
              seed: int = 0) -> Road:
    """Build the named road (see the module docstring) for ``duration_s`` at ``dt_s``."""
    for label, value in (("speed_mps", speed_mps), ("duration_s", duration_s),
                         ("dt_s", dt_s)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise RoadError(f"{label} must be a positive finite number, got {value!r}")
    n_ticks = round(duration_s / dt_s)
    if n_ticks < 1:
        raise RoadError(f"duration_s {duration_s} is shorter than one tick ({dt_s} s)")
    rng = np.random.default_rng(seed)
    length = speed_mps * n_ticks * dt_s
    dx = min(0.01, max(speed_mps * dt_s, 1e-3))   # >= 35 points per shortest wave
    key = name.strip()
    low = key.lower()
    if low.startswith("iso-") and len(low) == 5:
        gd = iso_gd(low[4])
        x, h = iso_spatial_profile(gd, length, dx, rng)
        return _finish(f"iso-{low[4].upper()}", speed_mps, dt_s,
                       _sample(x, h, speed_mps, n_ticks, dt_s), gd,
                       f"ISO 8608 class {low[4].upper()}, Gd(n0) = {gd:.3g} m^3")
    if low == "rough-course":
        gd = ROUGH_COURSE_RMS_M**2 / (ISO_N0**2 * (1 / ISO_N1 - 1 / ISO_N2))
        x, h = iso_spatial_profile(gd, length, dx, rng)
        return _finish("rough-course", speed_mps, dt_s,
                       _sample(x, h, speed_mps, n_ticks, dt_s), gd,
                       "ISO-shaped course scaled to 1.35 in RMS (Letourneau stand-in)")
    if low == "datp":
        gd = ISO_CLASSES["C"]
        x, h = iso_spatial_profile(gd, length, dx, rng)
        pos = 3.0
        while pos < x[-1]:
            blen = rng.uniform(0.5, 1.5)
            h = h + _cosine_bump(x, pos, blen, rng.uniform(0.04, 0.10))
            pos += blen + rng.uniform(4.0, 12.0)
        return _finish("datp", speed_mps, dt_s, _sample(x, h, speed_mps, n_ticks, dt_s),
                       gd, "bumpy DAT-P-like course: class C roughness + random bumps")
    s = np.arange(n_ticks + 1, dtype=np.float64) * dt_s * speed_mps
    if low == "bump":
        return _finish("bump", speed_mps, dt_s, _cosine_bump(s, 5.0, 1.0, 0.08), None,
                       "1-cos bump, 80 mm x 1 m, at 5 m")
    if low == "pothole":
        return _finish("pothole", speed_mps, dt_s, _pothole(s, 5.0, 0.6, 0.06, 0.05), None,
                       "pothole 60 mm deep, 0.6 m long, at 5 m")
    if low == "flat":
        return _finish("flat", speed_mps, dt_s, np.zeros(n_ticks + 1), None,
                       "road held at rest (shaker still: identification runs)")
    if low == "sweep":
        t = np.arange(n_ticks + 1) * dt_s
        f0, f1, v0 = 0.5, 25.0, 0.1
        T = n_ticks * dt_s
        rate = math.log(f1 / f0) / T
        f = f0 * np.exp(rate * t)
        phase = 2 * math.pi * f0 * (np.exp(rate * t) - 1.0) / rate
        return _finish("sweep", speed_mps, dt_s, v0 / (2 * math.pi * f) * np.sin(phase),
                       None, "log sine sweep 0.5-25 Hz, 0.1 m/s velocity amplitude")
    if key.startswith("csv:"):
        dist, height = _read_csv(key[4:], need_m=length)
        if dist[-1] - dist[0] < length:
            raise RoadError(f"road file {key[4:]!r} covers {dist[-1] - dist[0]:.1f} m but "
                            f"the run needs {length:.1f} m ({speed_mps} m/s x "
                            f"{n_ticks * dt_s} s)")
        return _finish(f"csv:{Path(key[4:]).name}", speed_mps, dt_s,
                       _sample(dist - dist[0], height, speed_mps, n_ticks, dt_s), None,
                       f"measured profile {key[4:]}")
    raise RoadError(f"unknown road {name!r}: use one of {', '.join(ROAD_NAMES)}")
