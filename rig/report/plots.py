"""The report's figures (matplotlib, Agg backend), one PNG each.

Every time plot shades the phases alike (:data:`PHASE_COLOURS`) and carries its legend
above the axes; each model of the bank has its own colour (:func:`model_colour`).  Plot
titles are the recording's message paths (``/rig/signals.rattlespace_m``), the syntax of
a Foxglove Plot panel, so a layout can show the same series.  Series longer than
:data:`MAX_PLOT_POINTS` are drawn as min/max envelopes (every extreme kept).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controller.arrays import FloatArray
from rig.report.events import EventRow
from rig.report.series import LIFECYCLE_NAMES, Phase, RunSeries
from rig.report.tracking import NO_FIRE_REACH_S, ForceTracking

__all__ = ["DPI", "MAX_PLOT_POINTS", "MODEL_COLOURS", "PHASE_ALPHA", "PHASE_COLOURS",
           "PHASE_TEXT", "WIDTH_IN", "Figure", "PlotInput", "envelope", "model_colour",
           "phase_handles", "render_all", "shade_phases", "window_stats"]

#: longest series drawn point by point; longer ones are drawn as a min/max envelope
MAX_PLOT_POINTS = 20_000
DPI = 96
WIDTH_IN = 10.0
#: phase shading, the same on every time plot and in the page's key
PHASE_COLOURS = {Phase.PASSIVE: "#9e9e9e", Phase.ACTIVE: "#2ca02c", Phase.FAULT: "#d62728"}
PHASE_ALPHA = 0.13
PHASE_TEXT = {Phase.PASSIVE: "passive (valve off)", Phase.ACTIVE: "active (valve driven)",
              Phase.FAULT: "fault latched (valve off)"}
#: one colour per model (none of them a phase colour); beyond 8 models the dash differs
MODEL_COLOURS = ("#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
                 "#bcbd22", "#393b79")
REF_COLOUR, MEAS_COLOUR, ERR_COLOUR, UNAPPLIED_COLOUR = "#222222", "#ff7f0e", "#9467bd", "#b0b0b0"
MODEL_WINDOW_S = 0.1
TIMING_WINDOW_S = 0.05


def model_colour(j: int) -> tuple[str, str]:
    """(colour, line style) of model ``j``."""
    n = len(MODEL_COLOURS)
    return MODEL_COLOURS[j % n], ("-", "--", ":", "-.")[(j // n) % 4]


@dataclass(frozen=True)
class Figure:
    """A PNG written by this module, with what the page says about it."""

    name: str                      # file name, also the element id (without .png)
    heading: str                   # plain words
    paths: tuple[str, ...]         # the recording's message paths it shows
    caption: str                   # HTML: what to read from it (not its title)


# ---------------------------------------------------------------------------- helpers


def envelope(t: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(t, lo, hi): min/max per bucket when longer than MAX_PLOT_POINTS, else (t, y, y)."""
    n = y.shape[0]
    if n <= MAX_PLOT_POINTS:
        return t, y, y
    b = math.ceil(n / (MAX_PLOT_POINTS // 2))
    m = n // b
    yy = y[: m * b].reshape(m, b)
    with np.errstate(all="ignore"), _quiet():
        return t[: m * b: b], np.nanmin(yy, axis=1), np.nanmax(yy, axis=1)


def window_stats(t: FloatArray, y: FloatArray, w: int, qs: Sequence[float] = ()
                 ) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
    """(t, mean, [percentile q ...]) over consecutive windows of ``w`` samples of the
    rows of ``y`` (shape (n,) or (n, J)); NaNs ignored, all-NaN windows give NaN."""
    w = max(1, int(w))
    m = y.shape[0] // w
    yy = y[: m * w].reshape(m, w, *y.shape[1:])
    with np.errstate(all="ignore"), _quiet():
        mean = np.nanmean(yy, axis=1)
        pct = [np.nanpercentile(yy, q, axis=1) for q in qs]
    return t[: m * w: w] + 0.5 * w * (t[1] - t[0] if t.size > 1 else 0.0), mean, pct


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence numpy's 'all-NaN slice' RuntimeWarnings inside a with-block."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def _line(ax: Any, t: FloatArray, y: FloatArray, **kw: Any) -> Any:
    """Draw y(t) (envelope when long); returns a handle for the legend."""
    tt, lo, hi = envelope(t, y)
    if lo is hi:
        return ax.plot(tt, lo, lw=kw.pop("lw", 0.7), **kw)[0]
    color = kw.pop("color", None)
    kw.pop("lw", None)
    label = kw.pop("label", None)
    poly = ax.fill_between(tt, lo, hi, alpha=kw.pop("alpha", 0.85), lw=0.5, color=color,
                           **kw)
    poly.set_edgecolor(poly.get_facecolor())
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, lw=1.5, label=label)


def shade_phases(ax: Any, s: RunSeries) -> None:
    """Shade every phase segment of ``s`` in its colour (behind the data)."""
    for g in s.segments:
        ax.axvspan(g.t_start_s, g.t_stop_s, color=PHASE_COLOURS[g.phase], alpha=PHASE_ALPHA,
                   lw=0, zorder=0)


def phase_handles(s: RunSeries) -> list[Any]:
    """Legend patches of the phases that occur in ``s``."""
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Patch

    seen = {g.phase for g in s.segments}
    return [Patch(facecolor=to_rgba(PHASE_COLOURS[p], PHASE_ALPHA),
                  edgecolor=PHASE_COLOURS[p], lw=0.8, label=p.label)
            for p in Phase if p in seen]


def _legend_columns(labels: Sequence[str], width_pt: float = 700.0) -> int:
    """Columns so that the legend's rows fit the figure width (8 pt text: ~4.6 pt per
    character plus handle and spacing; every column as wide as the widest label)."""
    longest = max((len(x) for x in labels), default=1) * 4.6 + 34.0
    return max(1, min(len(labels), int(width_pt // longest)))


def _title_and_legend(ax: Any, title: str, handles: Sequence[Any]) -> None:
    """Message path at the top left, the legend in rows between it and the axes."""
    labels = [h.get_label() for h in handles]
    ncol = _legend_columns(labels)
    rows = math.ceil(len(handles) / ncol) if handles else 0
    ax.set_title(title, loc="left", fontsize=9, family="monospace", pad=4 + 13 * rows)
    if handles:
        ax.legend(handles=list(handles), loc="lower left", bbox_to_anchor=(0.0, 1.0),
                  ncol=ncol, fontsize=8, frameon=False, handlelength=1.6,
                  columnspacing=1.2, borderaxespad=0.15, borderpad=0.1)


def _time_axes(ax: Any, s: RunSeries, xlabel: bool = True) -> None:
    shade_phases(ax, s)
    if s.t_s.size:
        ax.set_xlim(0.0, float(s.t_s[-1] + s.dt_s))
    ax.grid(True, lw=0.3, alpha=0.5)
    if xlabel:
        ax.set_xlabel("time since the first tick [s]")


def _fmt(v: float, digits: int = 3) -> str:
    return "–" if not math.isfinite(v) else f"{v:.{digits}g}"


# ---------------------------------------------------------------------------- figures


@dataclass
class PlotInput:
    s: RunSeries
    phases: dict[str, dict[str, float]]
    tracking: ForceTracking
    events: list[EventRow]
    compare: RunSeries | None = None


def render_all(d: PlotInput, out: Path) -> list[Figure]:
    """Write every figure that applies to ``d`` into ``out``; returns them in page order."""
    import matplotlib

    matplotlib.use("Agg")
    makers: list[Callable[[PlotInput, Path], Figure | None]] = [
        _summary, _rattlespace, _acceleration, _force, _force_tracking, _models,
        _sprung_mass, _lifecycle, _timing, _comparison]
    return [f for make in makers if (f := make(d, out)) is not None]


def _save(fig: Any, out: Path, name: str) -> None:
    """Every PNG is WIDTH_IN x DPI pixels wide (constrained layout, no trimming)."""
    import matplotlib.pyplot as plt

    fig.savefig(out / name, dpi=DPI)
    plt.close(fig)


def _subplots(nrows: int = 1, ncols: int = 1, height: float = 3.0, **kw: Any) -> Any:
    import matplotlib.pyplot as plt

    return plt.subplots(nrows, ncols, figsize=(WIDTH_IN, height), layout="constrained", **kw)


def _summary(d: PlotInput, out: Path) -> Figure | None:
    p, a = d.phases["passive"], d.phases["active"]
    if not (p["time_s"] > 0 and a["time_s"] > 0):
        return None
    items = [("absorbed_power_proxy", "absorbed power proxy", "(m/s²)²"),
             ("wk_rms_mps2", "Wk-weighted accel RMS", "m/s²"),
             ("rattlespace_rms_mm", "rattlespace RMS", "mm"),
             ("rattlespace_peak_mm", "rattlespace peak", "mm"),
             ("lateness_p99_us", "loop lateness p99", "µs")]
    fig, axs = _subplots(1, len(items), height=2.3)
    for ax, (key, label, unit) in zip(axs, items, strict=True):
        vals = [p[key], a[key]]
        bars = ax.bar([0, 1], [v if math.isfinite(v) else 0.0 for v in vals], width=0.7,
                      color=[PHASE_COLOURS[Phase.PASSIVE], PHASE_COLOURS[Phase.ACTIVE]])
        for bar, v in zip(bars, vals, strict=True):
            ax.annotate(_fmt(v), (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                        ha="center", va="bottom", fontsize=8, xytext=(0, 1),
                        textcoords="offset points")
        ratio = a[key] / p[key] if p[key] else math.nan
        ax.set_title(f"{label}\nactive / passive {_fmt(ratio)}", fontsize=8)
        ax.set_xticks([0, 1], ["passive", "active"], fontsize=8)
        ax.set_ylabel(unit, fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        ax.margins(y=0.2)
        for side in ("top", "right"):
            ax.spines[side].set_visible(False)
    _save(fig, out, "summary.png")
    return Figure("summary.png", "At a glance", ("/rig/signals", "/rig/timing"),
                  "Bars: metrics of the table below, passive (valve off, including time with "
                  "a fault latched) next to active. Lower absorbed power and Wk RMS mean a "
                  "smoother ride; the rattlespace must stay within the suspension travel.")


def _rattlespace(d: PlotInput, out: Path) -> Figure:
    s = d.s
    fig, ax = _subplots(height=2.9)
    h = _line(ax, s.t_s, 1e3 * s.signals["rattlespace_m"], color="#1f77b4",
              label="rattlespace_m")
    _time_axes(ax, s)
    ax.set_ylabel("rattlespace [mm]\n(compression +)")
    _title_and_legend(ax, "/rig/signals.rattlespace_m", [h, *phase_handles(s)])
    _save(fig, out, "rattlespace.png")
    p, a = d.phases["passive"], d.phases["active"]
    return Figure("rattlespace.png", "Rattlespace", ("/rig/signals.rattlespace_m",),
                  f"LVDT about the static position. RMS {_fmt(p['rattlespace_rms_mm'])} mm "
                  f"passive, {_fmt(a['rattlespace_rms_mm'])} mm active; peak "
                  f"{_fmt(p['rattlespace_peak_mm'])} mm passive, "
                  f"{_fmt(a['rattlespace_peak_mm'])} mm active.")


def _acceleration(d: PlotInput, out: Path) -> Figure:
    s = d.s
    fig, ax = _subplots(height=2.9)
    h = _line(ax, s.t_s, s.signals["sprung_accel_mps2"], color="#8c564b",
              label="sprung_accel_mps2")
    _time_axes(ax, s)
    ax.set_ylabel("sprung-mass accel\n[m/s²] (up +)")
    _title_and_legend(ax, "/rig/signals.sprung_accel_mps2", [h, *phase_handles(s)])
    _save(fig, out, "acceleration.png")
    p, a = d.phases["passive"], d.phases["active"]
    ratio = (a["absorbed_power_proxy"] / p["absorbed_power_proxy"]
             if p["absorbed_power_proxy"] else math.nan)
    return Figure("acceleration.png", "Sprung-mass acceleration",
                  ("/rig/signals.sprung_accel_mps2",),
                  f"Gravity removed. Absorbed power proxy {_fmt(p['absorbed_power_proxy'])} "
                  f"passive, {_fmt(a['absorbed_power_proxy'])} active (ratio "
                  f"{_fmt(ratio)}); Wk RMS {_fmt(p['wk_rms_mps2'])} and "
                  f"{_fmt(a['wk_rms_mps2'])} m/s².")


def _force(d: PlotInput, out: Path) -> Figure:
    s = d.s
    fig, (ax, ax2) = _subplots(2, 1, height=4.8, sharex=True,
                               gridspec_kw={"height_ratios": [2, 1]})
    off = s.signals["valve_enable"] <= 0
    h0 = _line(ax, s.t_s, 1e-3 * np.where(off, s.signals["force_ref_n"], np.nan),
               color=UNAPPLIED_COLOUR, label="force_ref_n computed, not applied", alpha=0.6)
    h1 = _line(ax, s.t_s, 1e-3 * s.force_ref_applied_n, color=REF_COLOUR,
               label="force_ref_n applied")
    h2 = _line(ax, s.t_s, 1e-3 * s.signals["force_meas_n"], color=MEAS_COLOUR,
               label="force_meas_n")
    _time_axes(ax, s, xlabel=False)
    ax.set_ylabel("force [kN]")
    _title_and_legend(ax, "/rig/signals.force_ref_n vs /rig/signals.force_meas_n",
                      [h1, h2, h0, *phase_handles(s)])
    h3 = _line(ax2, s.t_s, 1e-3 * s.tracking_error_n, color=ERR_COLOUR,
               label="force_ref_n applied − force_meas_n")
    _time_axes(ax2, s)
    ax2.set_ylabel("error [kN]")
    _title_and_legend(ax2, "tracking error (active)", [h3])
    _save(fig, out, "force.png")
    p, a = d.phases["passive"], d.phases["active"]
    lim = s.cfg.force_loop.force_limit_n
    return Figure(
        "force.png", "Force reference and measured force",
        ("/rig/signals.force_ref_n", "/rig/signals.force_meas_n",
         "/rig/signals.valve_enable"),
        f"Black: the force reference the PI force loop tracked, "
        f"<code>force_ref_n</code> while the valve is driven, limited to ±{lim:.0f} N "
        f"(<code>force_loop.force_limit_n</code>): "
        f"{_fmt(a['force_ref_applied_rms_n'], 4)} N RMS while active. Orange: the load "
        f"cell, {_fmt(a['force_meas_rms_n'], 4)} N RMS active, "
        f"{_fmt(p['force_meas_rms_n'], 3)} N passive. Purple: the tracking error, "
        f"{_fmt(a['tracking_error_rms_n'], 4)} N RMS (where it comes from: next figure). "
        f"Light grey: <code>force_ref_n</code> as recorded while the valve is off "
        f"({_fmt(p['force_ref_computed_rms_n'], 4)} N RMS). The bank computes it in every "
        f"state, but with the valve off the ValveCommand carries Enable = 0 and "
        f"ForceReference = 0 and the bypass is open: none of it reaches the actuator.")


def _force_tracking(d: PlotInput, out: Path) -> Figure | None:
    s, ft = d.s, d.tracking
    if not ft.ok:
        return None
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(WIDTH_IN, 6.6), layout="constrained")
    gs = fig.add_gridspec(2, 2, height_ratios=[1, 1.2])
    ax0 = fig.add_subplot(gs[0, :])
    # one second in the middle of the longest active segment, point by point
    seg = max((g for g in s.segments if g.phase is Phase.ACTIVE),
              key=lambda g: g.stop - g.start)
    w = min(seg.stop - seg.start, round(1.0 / s.dt_s))
    a = (seg.start + seg.stop - w) // 2
    sl = slice(a, a + w)
    t = s.t_s[sl]
    ax0.axvspan(t[0], t[-1] + s.dt_s, color=PHASE_COLOURS[Phase.ACTIVE], alpha=PHASE_ALPHA,
                lw=0, zorder=0)
    ref = 1e-3 * s.force_ref_applied_n[sl]
    hs = [ax0.plot(t, ref, color=REF_COLOUR, lw=0.8, label="force_ref_n applied")[0],
          ax0.plot(t, 1e-3 * s.signals["force_meas_n"][sl], color=MEAS_COLOUR, lw=1.3,
                   label="force_meas_n")[0],
          ax0.plot(t, 1e-3 * s.tracking_error_n[sl], color=ERR_COLOUR, lw=0.7,
                   label="error")[0]]
    nf = s.no_rule_fired[sl]
    if nf.any():
        hs.append(ax0.plot(t[nf], ref[nf], "o", ms=2.5, mfc="none", mec="#d62728", mew=0.7,
                           label="no fuzzy rule fired")[0])
    ax0.set_xlim(t[0], t[-1])
    ax0.set(xlabel="time since the first tick [s]", ylabel="force [kN]")
    ax0.grid(True, lw=0.3, alpha=0.5)
    _title_and_legend(ax0, "/rig/signals.force_ref_n, force_meas_n: one second, active",
                      [*hs, *phase_handles(s)[1:2]])

    ax1 = fig.add_subplot(gs[1, 0])
    f = ft.freq_hz
    m = f > 0
    for psd, colour, label, lw in ((ft.psd_ref, REF_COLOUR, "force_ref_n applied", 0.8),
                                   (ft.psd_meas, MEAS_COLOUR, "force_meas_n", 1.3),
                                   (ft.psd_error, ERR_COLOUR, "error", 0.8)):
        ax1.loglog(f[m], psd[m], color=colour, lw=lw, label=label)
    ax1.axvline(ft.corner_hz, color="k", ls="--", lw=0.8)
    ax1.annotate(f"force-loop corner\nkp·kq/2π = {ft.corner_hz:.0f} Hz",
                 (ft.corner_hz, 1.0), xycoords=("data", "axes fraction"), xytext=(4, -4),
                 textcoords="offset points", va="top", fontsize=7)
    ax1.set(xlabel="frequency [Hz]", ylabel="PSD [N²/Hz]")
    ax1.grid(True, which="both", lw=0.3, alpha=0.4)
    ax1.set_title("spectra while active", loc="left", fontsize=9)
    ax1.legend(fontsize=7, loc="lower left", frameon=False)

    ax2 = fig.add_subplot(gs[1, 1])
    x, y = ft.rate_mps, ft.error_low_n
    step = max(1, x.size // 6000)
    ax2.scatter(x[::step], 1e-3 * y[::step], s=2, color=ERR_COLOUR, alpha=0.25, lw=0,
                rasterized=True)
    lim = float(np.percentile(np.abs(x), 99.5)) if x.size else 1.0
    xs = np.array([-lim, lim])
    ax2.plot(xs, -1e-3 * ft.oil_column_ns_per_m * xs, color="#888888", ls=":", lw=1.0,
             label=f"no feedforward: −k_h/(kp·kq) = {_slope(ft.oil_column_ns_per_m)}")
    ax2.plot(xs, -1e-3 * ft.residual_slope_ns_per_m * xs, color="k", ls="--", lw=1.0,
             label=f"with feedforward g = {ft.feedforward_gain:g}: "
                   f"{_slope(ft.residual_slope_ns_per_m)} (config)")
    ax2.plot(xs, -1e-3 * ft.fitted_slope_ns_per_m * xs, color=ERR_COLOUR, lw=1.0,
             label=f"least squares: {_slope(ft.fitted_slope_ns_per_m)}")
    ax2.set_xlim(-lim, lim)
    ax2.set(xlabel="d/dt rattlespace_m [m/s] (low-passed)",
            ylabel=f"error below {ft.corner_hz:.0f} Hz [kN]")
    ax2.grid(True, lw=0.3, alpha=0.5)
    ax2.set_title("error vs rattlespace rate while active", loc="left", fontsize=9)
    ax2.legend(fontsize=7, loc="upper right", frameon=False)
    _save(fig, out, "force_tracking.png")
    return Figure(
        "force_tracking.png", "Where the force-tracking error comes from",
        ("/rig/signals.force_ref_n", "/rig/signals.force_meas_n",
         "/rig/signals.rattlespace_m", "/controller/internals.flags"),
        _tracking_caption(ft))


def _slope(ns_per_m: float) -> str:
    """A slope d(error)/d(rate) of ``-ns_per_m`` as text with a true minus sign."""
    v = -ns_per_m / 1e3
    if not math.isfinite(v):
        return "–"
    return f"{'−' if v < 0 else ''}{abs(v):.2f} kN·s/m"


def _tracking_caption(ft: ForceTracking) -> str:
    design = ("By design: the LQ gains were designed on this actuator under the P path "
              "(<code>design.actuator_model = \"hydraulic\"</code>), so "
              "<code>force_ref_n</code> is the input of the force loop, not a force the "
              "actuator is expected to reproduce."
              if ft.designed_for_actuator else
              "The LQ gains were designed for an ideal force source "
              "(<code>design.actuator_model = \"ideal\"</code>), so this part is control "
              "authority lost to the actuator.")
    explained = (f"it accounts for {100 * ft.explained_below:.0f} % of the error "
                 f"variance below the corner" if ft.explained_below >= 0.05 else
                 "it accounts for almost none of the error below the corner")
    low = (f"<li><b>Below the force loop's corner</b> (kp·kq/2π = {ft.corner_hz:.0f} Hz): "
           f"{ft.error_rms_below_n:.0f} N RMS. Two parts. <i>The oil column</i>: without "
           f"help the proportional path would have to open the valve just to keep the oil "
           f"moving with the suspension, an error of −k_h/(kp·kq) = "
           f"{_slope(ft.oil_column_ns_per_m)} × d/dt rattlespace_m (dotted, right); the "
           f"valve flow feedforward (<code>force_loop.flow_feedforward_gain</code> = "
           f"{ft.feedforward_gain:g}) supplies that flow, leaving "
           f"{_slope(ft.residual_slope_ns_per_m)} (dashed; recorded configuration, not "
           f"fitted): {explained} (least squares {_slope(ft.fitted_slope_ns_per_m)}). "
           f"<i>The loop's lag</i>: a first-order loop with this corner, following this "
           f"reference, leaves {ft.lag_error_rms_below_n:.0f} N RMS of error below the "
           f"corner (from the reference's spectrum, left; the measured force visibly lags "
           f"the reference, top); what this simple model leaves out (the spool's own "
           f"dynamics, the {ft.delay_ticks} tick(s) of compute delay) lags more. "
           f"{design}</li>")
    high = (f"<li><b>Above the corner</b>: {ft.error_rms_above_n:.0f} N RMS, the "
            f"reference's own content ({ft.ref_rms_above_n:.0f} N RMS there) that the "
            f"loop does not follow (measured force {ft.meas_rms_above_n:.0f} N there).")
    if math.isfinite(ft.no_fire_share) and ft.no_fire_share > 0:
        high += (f" On {100 * ft.no_fire_share:.1f} % of the active ticks no fuzzy rule "
                 f"fired and the reference dropped to the fallback force for that tick "
                 f"(<code>fuzzy.no_fire_fallback</code>; red circles, top). Within "
                 f"{1e3 * NO_FIRE_REACH_S:.0f} ms of such a tick "
                 f"({100 * ft.near_no_fire_share:.0f} % of the active time) the reference "
                 f"has {ft.ref_rms_above_near_no_fire_n:.0f} N RMS above the corner, "
                 f"elsewhere {ft.ref_rms_above_elsewhere_n:.0f} N.")
    return (f"While active ({ft.active_s:.1f} s) the tracking error is "
            f"{ft.error_rms_n:.0f} N RMS against {ft.meas_rms_n:.0f} N RMS of measured "
            f"force:<ul>{low}{high}</li></ul>")


def _models(d: PlotInput, out: Path) -> Figure | None:
    s = d.s
    J = s.per_model["q"].shape[1]
    if not J:
        return None
    w = max(round(MODEL_WINDOW_S / s.dt_s), math.ceil(s.t_s.size / MAX_PLOT_POINTS))
    win_ms = 1e3 * w * s.dt_s
    tw, fw_mean, _ = window_stats(s.t_s, s.per_model["firing_weight"], w)
    q = np.where(s.per_model["q"] > 0, s.per_model["q"], np.nan)
    _, _, (q_lo, q_med, q_hi) = window_stats(s.t_s, q, w, (10, 50, 90))
    # the models whose filter ran (q > 0 at some tick): a layered bank runs one layer of
    # its many models at a time (docs/design.md §11)
    ran = [j for j in range(J) if np.any(s.per_model["q"][:, j] > 0)] or list(range(J))
    fig, (ax, ax2) = _subplots(2, 1, height=5.6, sharex=True)
    handles = []
    for j in ran:
        colour, ls = model_colour(j)
        handles.append(ax.plot(tw, fw_mean[:, j], color=colour, ls=ls, lw=1.1,
                               label=f"[{j}] {s.model_names[j]}")[0])
        ax2.fill_between(tw, q_lo[:, j], q_hi[:, j], color=colour, alpha=0.12, lw=0)
        ax2.plot(tw, q_med[:, j], color=colour, ls=ls, lw=1.1)
    if np.any(s.flags >= 0):
        _, nf_share, _ = window_stats(s.t_s, s.no_rule_fired.astype(float), w)
        handles.append(ax.plot(tw, nf_share, color="k", ls=":", lw=1.0,
                               label="no rule fired (share of ticks)")[0])
    _time_axes(ax, s, xlabel=False)
    ax.set_ylim(-0.03, 1.03)
    ax.set_ylabel(f"firing weight\n({win_ms:.0f} ms means)")
    _title_and_legend(ax, "/controller/internals.firing_weight[j]", handles)
    _time_axes(ax2, s)
    if np.isfinite(q).any():     # no positive q (e.g. the bank never ran): linear
        ax2.set_yscale("log")
    ax2.set_ylabel(f"q (median and\n10–90 % of {win_ms:.0f} ms)")
    _title_and_legend(ax2, "/controller/internals.q[j]", phase_handles(s))
    _save(fig, out, "models.png")
    active = s.phase == Phase.ACTIVE
    with _quiet():
        mean_w = (np.nanmean(s.per_model["firing_weight"][active], axis=0) if active.any()
                  else np.full(J, np.nan))
    rows = ", ".join(f"{s.model_names[j]} {_fmt(mean_w[j], 2)}" for j in ran)
    which = (f"The design's {J} linear tire models, one colour each" if len(ran) == J else
             f"The {len(ran)} of the design's {J} linear models whose filter ran (the "
             f"layers the bank ran), one colour each")
    return Figure(
        "models.png", "Firing weights and likelihood quotients per model",
        ("/controller/internals.firing_weight", "/controller/internals.q",
         "/controller/internals.flags"),
        f"{which}. Firing weights are the "
        f"normalised blending weights actually used (sum 1 unless no rule fired); mean "
        f"while active: {rows}. q is each model's likelihood quotient (log scale; small "
        f"q: the model explains the measurements).")


def _sprung_mass(d: PlotInput, out: Path) -> Figure | None:
    """The controller's sprung-mass estimate over the run, against the configured mass
    (and, for a layered bank, the mass of the layer it ran)."""
    s = d.s
    m = s.sprung_mass_est_kg
    if m.size != s.t_s.size or not np.isfinite(m).any():
        return None
    fig, ax = _subplots(1, 1, height=2.6)
    handles = [_line(ax, s.t_s, m, color="C0", lw=1.1, label="estimate")]
    nominal = s.cfg.vehicle.sprung_mass_kg
    handles.append(ax.axhline(nominal, color="k", ls="--", lw=0.8,
                              label=f"configured {nominal:g} kg"))
    layered = s.layer_mkc.shape[0] == s.t_s.size and bool(np.isfinite(s.layer_mkc).any())
    if layered:
        handles.append(ax.step(s.t_s, s.layer_mkc[:, 0], where="post", color="C3", lw=1.0,
                               label="the running layer's mass")[0])
    _time_axes(ax, s)
    ax.set_ylabel("sprung mass [kg]")
    _title_and_legend(ax, "/controller/internals.sprung_mass_est_kg",
                      [*handles, *phase_handles(s)])
    _save(fig, out, "sprung_mass.png")
    fin = m[np.isfinite(m)]
    return Figure(
        "sprung_mass.png", "Sprung-mass estimate",
        ("/controller/internals.sprung_mass_est_kg",
         *(("/controller/internals.models",) if layered else ())),
        f"What the controller believes the body weighs (least squares on the body equation "
        f"M a = F + K z + C z', docs/design.md §10): {_fmt(fin[-1], 4)} kg at the end, "
        f"{_fmt(float(fin.min()), 4)}–{_fmt(float(fin.max()), 4)} kg over the run, against "
        f"the configured {nominal:g} kg. It holds while the rig is too quiet to tell."
        + (_layers_caption(s) if layered else ""))


def _layers_caption(s: RunSeries) -> str:
    """The layers a layered bank ran (docs/design.md §11), longest first, with the time
    on each (by the loop clock)."""
    dt = np.diff(s.t_s, append=s.t_s[-1])
    ok = np.all(np.isfinite(s.layer_mkc), axis=1)
    keys, inverse = np.unique(s.layer_mkc[ok], axis=0, return_inverse=True)
    time_s = np.bincount(inverse.ravel(), weights=dt[ok], minlength=len(keys))
    order = np.argsort(-time_s)
    parts = [f"{keys[i, 0]:.0f} kg, {keys[i, 1]:.0f} N/m, {keys[i, 2]:.0f} N s/m for "
             f"{time_s[i]:.1f} s" for i in order[:6]]
    more = f" and {len(keys) - 6} more" if len(keys) > 6 else ""
    return (f" The bank ran {len(keys)} of its layers (the red line is the running layer's "
            f"mass; each layer is the design for one sprung mass, spring rate and damping): "
            f"{'; '.join(parts)}{more}.")


def _lifecycle(d: PlotInput, out: Path) -> Figure:
    s = d.s
    fig, ax = _subplots(height=2.8)
    code = np.array([LIFECYCLE_NAMES.index(x) if x in LIFECYCLE_NAMES else np.nan
                     for x in s.lifecycle])
    h = ax.step(s.t_s, code, where="post", color="k", lw=1.0, label="lifecycle")[0]
    _time_axes(ax, s)
    ax.set_yticks(range(len(LIFECYCLE_NAMES)), LIFECYCLE_NAMES, fontsize=8)
    ax.set_ylim(-0.5, len(LIFECYCLE_NAMES) - 0.5)
    kind_colour = {"fault": PHASE_COLOURS[Phase.FAULT], "command": "#1f77b4"}
    label_them = len(d.events) <= 40
    span = float(s.t_s[-1] + s.dt_s) if s.t_s.size else 1.0
    last_x, level = -math.inf, 0
    for e in d.events:
        if not math.isfinite(e.t_s):
            continue
        c = kind_colour.get(e.kind, "#555555")
        ax.axvline(e.t_s, color=c, lw=0.8, alpha=0.8)
        if label_them:  # numbers close together step down instead of overprinting
            level = level + 1 if e.t_s - last_x < 0.015 * span and level < 5 else 0
            last_x = e.t_s
            ax.annotate(str(e.number), (e.t_s, 1.0), xycoords=("data", "axes fraction"),
                        xytext=(2, -2 - 9 * level), textcoords="offset points", va="top",
                        fontsize=7, color=c)
    from matplotlib.lines import Line2D

    marks = [Line2D([], [], color=kind_colour["fault"], lw=1, label="fault event"),
             Line2D([], [], color=kind_colour["command"], lw=1, label="command"),
             Line2D([], [], color="#555555", lw=1, label="other event")]
    _title_and_legend(ax, "/rig/signals.lifecycle, /rig/events",
                      [h, *marks, *phase_handles(s)])
    _save(fig, out, "lifecycle.png")
    times = "; ".join(f"{PHASE_TEXT[p]} {s.time_in(p):.2f} s" for p in Phase
                      if s.time_in(p) > 0)
    return Figure("lifecycle.png", "Lifecycle and events",
                  ("/rig/signals.lifecycle", "/rig/events"),
                  f"The numbers are the rows of the events table. Time per phase: {times}.")


def _timing(d: PlotInput, out: Path) -> Figure | None:
    s = d.s
    late = s.timing["wake_late_s"] * 1e6
    comp = s.timing["compute_s"] * 1e6
    if not (np.isfinite(late).any() or np.isfinite(comp).any()):
        return None
    floor = 1.0        # µs; the log axes show shorter times here
    w = max(1, round(TIMING_WINDOW_S / s.dt_s))
    fig, (ax, axh) = _subplots(1, 2, height=3.0, width_ratios=[3, 1])
    hs = []
    for y, colour, label in ((late, "#1f77b4", "wake_late_s"), (comp, "#ff7f0e", "compute_s")):
        tw, _, (hi,) = window_stats(s.t_s, np.maximum(y, floor), w, (100,))
        hs.append(ax.plot(tw, hi, color=colour, lw=0.8,
                          label=f"{label} (max per {1e3 * w * s.dt_s:.0f} ms)")[0])
    thr = s.cfg.safety.overrun_threshold_s * 1e6
    hs.append(ax.axhline(thr, color="k", ls="--", lw=0.8,
                         label=f"overrun threshold {thr:.0f} µs"))
    _time_axes(ax, s)
    ax.set_yscale("log")
    ax.set_ylabel("µs")
    _title_and_legend(ax, "/rig/timing.wake_late_s, compute_s", [*hs, *phase_handles(s)])
    for y, colour in ((late, "#1f77b4"), (comp, "#ff7f0e")):
        y = y[np.isfinite(y)]
        if y.size:
            axh.hist(np.maximum(y, floor), bins=np.geomspace(floor, max(y.max(), 10.0), 60),
                     color=colour, alpha=0.6, orientation="horizontal")
    axh.set_yscale("log")
    axh.set_xscale("log")
    axh.set_ylim(ax.get_ylim())
    axh.set_xlabel("ticks")
    axh.set_title("every tick", loc="left", fontsize=9)
    axh.grid(True, lw=0.3, alpha=0.5)
    _save(fig, out, "timing.png")
    p, a = d.phases["passive"], d.phases["active"]
    finite = late[np.isfinite(late)]
    worst = float(finite.max()) if finite.size else math.nan
    overruns = int(p["overrun_ticks"] + a["overrun_ticks"])
    return Figure("timing.png", "Loop timing", ("/rig/timing.wake_late_s",
                                                "/rig/timing.compute_s"),
                  f"Wake-up lateness and compute time per tick; times under {floor:.0f} µs "
                  f"are drawn at {floor:.0f} µs. Lateness p99 {_fmt(p['lateness_p99_us'])} µs "
                  f"passive, {_fmt(a['lateness_p99_us'])} µs active, worst "
                  f"{worst / 1e3:.1f} ms; {overruns} overrun ticks.")


def _comparison(d: PlotInput, out: Path) -> Figure | None:
    s, other = d.s, d.compare
    if other is None:
        return None
    fig, ax = _subplots(height=3.0)
    k = np.intersect1d(s.tick, other.tick)
    a = np.searchsorted(other.tick, k)
    b = np.searchsorted(s.tick, k)
    tt = s.t_s[b] if k.size else np.zeros(0)
    h1 = _line(ax, tt, 1e-3 * other.signals["force_ref_n"][a], color=UNAPPLIED_COLOUR,
               label="recorded controller")
    h2 = _line(ax, tt, 1e-3 * s.signals["force_ref_n"][b], color="#d62728",
               label="replayed controller")
    _time_axes(ax, s)
    ax.set_ylabel("force_ref_n [kN]")
    _title_and_legend(ax, "/rig/signals.force_ref_n: recorded vs replayed",
                      [h1, h2, *phase_handles(s)])
    _save(fig, out, "comparison.png")
    return Figure("comparison.png", "Recorded vs replayed controller (open loop)",
                  ("/rig/signals.force_ref_n",),
                  "The same sensor data through two controllers: the replayed one never "
                  "acted on the rig, so its differences do not feed back.")
