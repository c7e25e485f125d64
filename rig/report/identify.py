"""The identification report (``rig identify RUN --report FILE.html``): one HTML file,
its figures embedded as PNG data URIs, built with the run report's page style and plot
helpers (:mod:`rig.report.page`, :mod:`rig.report.plots`).

Figures: the measured frequency responses from the actuator force to the body
acceleration and to the rattlespace (Welch cross-spectra against the excitation, bins
with coherence > 0.8 drawn solid) with the identified model's (python-control), magnitude
and phase; the filtered body force against the fit M a - K r - C r' (two windows: the
chirp's start and its end); the residual over the run and its histogram.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from rig.report.page import _SCRIPT, _css, fmt_num
from rig.report.plots import DPI, MODEL_COLOURS, _subplots

__all__ = ["IDENTIFY_FIGURES", "write_identify_report"]

#: figure ids in page order
IDENTIFY_FIGURES = ("bode", "force_fit", "residual")
MEASURED_COLOUR = MODEL_COLOURS[0]
MODEL_COLOUR = MODEL_COLOURS[1]


def _png(fig: Any) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _bode(c: dict[str, np.ndarray]) -> str:
    fig, axes = _subplots(2, 2, height=6.0, sharex=True)
    f = c["f_hz"]
    band = (f >= 0.3) & (f <= 40.0)
    for col, (name, unit) in enumerate((("a", "(m/s²)/N"), ("r", "m/N"))):
        meas, model, coh = c[f"H_{name}_meas"], c[f"H_{name}_model"], c[f"coh_{name}"]
        good = band & (coh > 0.8)
        for ax, part, label in ((axes[0, col], np.abs, f"|F → {name}| [{unit}]"),
                                (axes[1, col], lambda h: np.degrees(np.unwrap(np.angle(h))),
                                 f"phase F → {name} [deg]")):
            ax.plot(f[band], part(meas[band]), ".", ms=2, color=MEASURED_COLOUR, alpha=0.3)
            ax.plot(f[good], part(meas[good]), ".", ms=4, color=MEASURED_COLOUR,
                    label="measured (coherence > 0.8)")
            ax.plot(f[band], part(model[band]), "-", lw=1.5, color=MODEL_COLOUR,
                    label="identified model")
            ax.set_xscale("log")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
            if part is np.abs:
                ax.set_yscale("log")
        axes[1, col].set_xlabel("frequency [Hz]")
    axes[0, 0].legend(loc="best", fontsize=8)
    return _png(fig)


def _force_fit(c: dict[str, np.ndarray]) -> str:
    fig, axes = _subplots(1, 2, height=3.2)
    t = c["t_s"]
    for ax, (a, b) in zip(axes, ((t[0] + 1.0, t[0] + 4.0), (t[-1] - 1.0, t[-1] - 0.5)),
                          strict=True):
        sel = (t >= a) & (t <= b)
        ax.plot(t[sel], c["force_filtered_n"][sel], color=MEASURED_COLOUR, lw=1.2,
                label="measured force (filtered)")
        ax.plot(t[sel], c["force_fitted_n"][sel], "--", color=MODEL_COLOUR, lw=1.2,
                label="M a - K r - C r'")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("force [N]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    return _png(fig)


def _residual(c: dict[str, np.ndarray]) -> str:
    fig, axes = _subplots(1, 2, height=3.0, width_ratios=[3, 1])
    t, res = c["t_s"], c["residual_n"]
    axes[0].plot(t, res, color=MEASURED_COLOUR, lw=0.4)
    axes[0].set_xlabel("time [s]")
    axes[0].set_ylabel("body equation residual [N]")
    axes[0].grid(True, alpha=0.3)
    axes[1].hist(res, bins=60, color=MEASURED_COLOUR, orientation="horizontal")
    axes[1].set_xlabel("ticks")
    return _png(fig)


def _table(ident: Any) -> str:
    rows = []
    for key, value in ident.estimates.items():
        lo, hi = ident.ci95[key]
        rel = (100 * (hi - lo) / 2 / abs(value) if abs(value) > (hi - lo) / 2
               else math.nan)       # an offset near 0: no relative width
        rows.append(f"<tr><td><code>{html.escape(key)}</code></td><td>{fmt_num(value, 6)}"
                    f"</td><td>[{fmt_num(lo, 6)}, {fmt_num(hi, 6)}]</td>"
                    f"<td>{fmt_num(rel, 3)}</td></tr>")
    for key, why in ident.not_identified.items():
        rows.append(f"<tr class='ev-fault'><td><code>{html.escape(key)}</code></td>"
                    f"<td colspan='3'>{html.escape(why)}</td></tr>")
    return ("<table><tr><th>config key</th><th>estimate</th><th>95 % interval</th>"
            "<th>± %</th></tr>" + "".join(rows) + "</table>")


def write_identify_report(ident: Any, path: str | Path, run_name: str) -> Path:
    """Write the report of ``ident`` (:class:`controller.identify.Identification`)."""
    c = ident.curves
    figs = {"bode": (_bode(c), "Measured (dots; faint where the coherence is below 0.8) "
                               "and identified-model frequency responses from the "
                               "actuator force."),
            "force_fit": (_force_fit(c), "Body equation: the filtered load cell force "
                                         "against the identified M a - K r - C r' at the "
                                         "chirp's start and end."),
            "residual": (_residual(c), "Residual of the body equation over the excitation "
                                       "and its distribution.")}
    fit = ident.fit
    fd = fit["frequency_domain"]["relative_difference"]
    cross = ", ".join(f"{html.escape(k)} {100 * v:+.2f} %" for k, v in fd.items())
    body = "".join(
        f"<figure id='{name}'><img alt='{name}' src='data:image/png;base64,{png}'>"
        f"<figcaption>{html.escape(cap)}</figcaption></figure>"
        for name, (png, cap) in figs.items())
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Identification {html.escape(run_name)}
</title><style>{_css()}</style>{_SCRIPT}</head><body>
<h1>Identification of {html.escape(run_name)}</h1>
<p class="lede">{fit['excitation_s']:.1f} s of excitation, {fit['rest_s']:.1f} s of rest;
body fit R² {fmt_num(fit['body_fit_r2'], 6)}. {html.escape(fit['method'])}.</p>
<h2>Estimates</h2>{_table(ident)}
<p>Frequency-domain cross-check (Welch, {fit['frequency_domain']['bins']} bins), relative
to the time domain: {cross}.</p>
<h2>Responses, traces, residuals</h2>{body}
</body></html>
"""
    out = Path(path)
    out.write_text(page, encoding="utf-8")
    return out
