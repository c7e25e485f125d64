"""The report's HTML page (``index.html``) around the PNGs of :mod:`rig.report.plots`."""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

from controller.runtime.kernels import Blending
from rig.output_paths import staged_dir
from rig.replay import OPEN_LOOP_NOTE, RecordingError
from rig.report.events import EventRow, event_rows
from rig.report.metrics import SUMMARY_ROWS, phase_metrics, run_metrics
from rig.report.plots import (
    PHASE_ALPHA,
    PHASE_COLOURS,
    PHASE_TEXT,
    Figure,
    PlotInput,
    model_colour,
    render_all,
)
from rig.report.series import Phase, RunSeries, load_series
from rig.report.tracking import force_tracking

__all__ = ["write_report"]

#: most event rows shown (the rest are counted)
MAX_EVENT_ROWS = 500
_SECTIONS = (  # section heading, figures in it
    ("Ride", ("rattlespace.png", "acceleration.png")),
    ("Force", ("force.png", "force_tracking.png")),
    ("Controller bank", ("models.png", "sprung_mass.png")),
    ("Lifecycle and loop timing", ("lifecycle.png", "timing.png")),
    ("Replay", ("comparison.png",)),
)

_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
  }
  document.body.setAttribute('data-images-loaded', ok + '/' + imgs.length);
});
</script>"""


def fmt_num(v: Any, digits: int = 4) -> str:
    """A number for a table: "–" if missing, thousands separated when large."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return html.escape(str(v))
    if isinstance(v, int):
        return f"{v:,}"
    if not math.isfinite(v):
        return "–"
    if abs(v) >= 10 ** digits:
        return f"{v:,.0f}"
    return f"{v:.{digits}g}"


def _rgba(colour: str, alpha: float) -> str:
    r, g, b = (int(colour[i:i + 2], 16) for i in (1, 3, 5))
    return f"rgba({r}, {g}, {b}, {alpha})"


def _css() -> str:
    phase = "\n".join(
        f".ph-{p.label} {{ background: {_rgba(c, PHASE_ALPHA)}; border-color: {c}; }}"
        for p, c in PHASE_COLOURS.items())
    return f"""
body {{ font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1000px;
       padding: 0 1em; color: #222; }}
h1 {{ margin-bottom: 0.2em; }} h2 {{ margin-top: 1.6em; border-bottom: 1px solid #ddd; }}
h3 {{ margin: 0.2em 0; font-size: 1.0em; }}
.lede {{ color: #444; margin-top: 0; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1em; }}
th, td {{ border: 1px solid #ccc; padding: 2px 8px; text-align: left; font-size: 88%;
         vertical-align: top; }}
thead th {{ background: #f3f3f3; }}
td.num {{ text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }}
td.src, td.details {{ font-size: 80%; color: #555; }}
code, td.src {{ font-family: ui-monospace, monospace; }}
.warn {{ background: #fff3cd; padding: 0.5em; border: 1px solid #e0c060; }}
.key span.sw {{ display: inline-block; width: 1.6em; height: 0.9em; border: 1px solid;
               vertical-align: middle; margin: 0 0.3em 0 0.8em; }}
.model {{ border-bottom: 3px solid var(--c); padding: 0 2px; }}
figure {{ margin: 1.2em 0; }} img {{ max-width: 100%; }}
figcaption {{ font-size: 90%; color: #333; max-width: 60em; }}
.channels {{ font-size: 80%; color: #555; margin: 0 0 0.3em; }}
h3 a {{ color: inherit; text-decoration: none; }}
tr.ev-fault td {{ background: {_rgba(PHASE_COLOURS[Phase.FAULT], PHASE_ALPHA)}; }}
{phase}
"""


def _run_facts(s: RunSeries, metrics: dict[str, Any]) -> str:
    meta = s.scan.rig_metadata          # the loop settings: rig.service.assembly
    facts = [html.escape(meta.get("source", "recording"))]
    if meta.get("road"):
        speed = meta.get("speed_mps")
        facts.append(f"road {html.escape(meta['road'])}"
                     + (f" at {float(speed):.2f} m/s" if speed else ""))
    facts.append(f"{metrics['duration_s']:.2f} s, {metrics['ticks']:,} ticks")
    blending = str(meta.get("blending"))
    if blending.isdigit() and int(blending) in Blending._value2member_map_:
        facts.append(f"{Blending(int(blending)).name.lower()} blending")
    ws = meta.get("weight_set")
    if ws is not None:
        facts.append(f"weight set {html.escape(str(ws))}"
                     + (" (travel schedule)" if str(ws) == "0" else ""))
    models = " ".join(
        f'<span class="model" style="--c:{model_colour(j)[0]}">{html.escape(n)}</span>'
        for j, n in enumerate(s.model_names))
    if models:
        facts.append(f"models {models}")
    n_faults = int(metrics["faults"])
    facts.append(f"{n_faults} fault{'s' if n_faults != 1 else ''}")
    return " · ".join(facts)


def _phase_key(s: RunSeries) -> str:
    items = "".join(
        f'<span class="sw ph-{p.label}"></span>{html.escape(PHASE_TEXT[p])} '
        f"{s.time_in(p):.2f} s" for p in Phase if s.time_in(p) > 0)
    return f'<p class="key">Shaded on every time plot:{items}</p>'


def _summary_table(phases: dict[str, dict[str, float]]) -> str:
    p, a = phases["passive"], phases["active"]
    rows = []
    for r in SUMMARY_ROWS:
        pv, av = p[r.key], a[r.key]
        ratio = av / pv if (r.ratio and math.isfinite(pv) and math.isfinite(av)
                            and pv != 0) else math.nan
        unit = f" [{html.escape(r.unit)}]" if r.unit else ""
        rows.append(f"<tr><th>{html.escape(r.label)}{unit}</th>"
                    f'<td class="num">{fmt_num(pv, r.digits)}</td>'
                    f'<td class="num">{fmt_num(av, r.digits)}</td>'
                    f'<td class="num">{fmt_num(ratio, 3)}</td>'
                    f'<td class="src">{html.escape(r.source)}</td></tr>')
    return ('<table class="summary"><thead><tr><th>metric</th>'
            f'<th class="ph-passive">passive (valve off)</th><th class="ph-active">active</th>'
            "<th>active / passive</th><th>from</th></tr></thead>"
            f"<tbody>{''.join(rows)}</tbody></table>")


def _events_table(rows: list[EventRow]) -> str:
    if not rows:
        return "<p>No events were recorded.</p>"
    body = []
    for e in rows[:MAX_EVENT_ROWS]:
        body.append(
            f'<tr class="ev-{html.escape(e.kind)}"><td class="num">{e.number}</td>'
            f'<td class="num">{fmt_num(e.t_s, 6) if math.isfinite(e.t_s) else "–"}</td>'
            f'<td class="num">{e.tick}</td><td>{html.escape(e.kind)}</td>'
            f"<td>{html.escape(e.change)}</td><td><code>{html.escape(e.code)}</code></td>"
            f"<td>{html.escape(e.reason)}</td>"
            f'<td class="details">{html.escape(e.details)}</td></tr>')
    more = (f"<p>{len(rows) - MAX_EVENT_ROWS:,} more events not shown.</p>"
            if len(rows) > MAX_EVENT_ROWS else "")
    return ('<table class="events"><thead><tr><th>#</th><th>t [s]</th><th>tick</th>'
            "<th>event</th><th>state change</th><th>code</th><th>reason</th>"
            f"<th>details</th></tr></thead><tbody>{''.join(body)}</tbody></table>{more}")


def _figure(f: Figure) -> str:
    stem = f.name.removesuffix(".png")
    chans = " ".join(f'<code class="chan">{html.escape(p)}</code>' for p in f.paths)
    return (f'<figure id="fig-{stem}" data-paths="{html.escape(" ".join(f.paths))}">'
            f'<h3><a href="#fig-{stem}">{html.escape(f.heading)}</a></h3>'
            f'<p class="channels">Channels (the same names in the MCAP recording and the '
            f"live Foxglove view, docs/foxglove.md): {chans}</p>"
            f'<img src="{f.name}" alt="{html.escape(f.heading)}">'
            f"<figcaption>{f.caption}</figcaption></figure>")


def write_report(path: str | Path, out_dir: str | Path | None = None,
                 compare: str | Path | None = None) -> Path:
    """Write the report of recording ``path`` into ``out_dir`` (default: next to the
    recording, ``<stem>-report/``); returns the HTML file.  ``compare`` (default: the
    source of a replay, if it exists) adds the recorded-vs-replayed controller plot."""
    s = load_series(path)
    empty = s.no_sensor_data()
    if empty:
        raise RecordingError(f"{path}: {empty}; nothing to report")
    out = Path(out_dir) if out_dir is not None else Path(path).with_name(
        f"{Path(path).stem}-report")
    with staged_dir(out) as stage:
        _write_page(s, path, compare, stage)
    return out / "index.html"


def _write_page(s: RunSeries, path: str | Path, compare: str | Path | None,
                out: Path) -> None:
    meta = s.scan.rig_metadata
    replay_of = meta.get("replay_of")
    open_loop = meta.get("open_loop") == "true"
    if compare is None and replay_of and open_loop and Path(replay_of).exists():
        compare = replay_of
    other = load_series(compare) if compare is not None else None
    events = event_rows(s)
    figures: list[Figure] = []
    phases: dict[str, dict[str, float]] = {}
    metrics: dict[str, Any] = {"duration_s": 0.0, "ticks": 0, "faults": 0}
    if s.tick.size:
        metrics = run_metrics(s)
        phases = phase_metrics(s)
        figures = render_all(PlotInput(s, phases, force_tracking(s), events, other), out)
    by_name = {f.name: f for f in figures}

    banner = ""
    if open_loop:
        banner += (f'<p class="warn"><b>Replay, {html.escape(OPEN_LOOP_NOTE)}.</b> '
                   f"Source: {html.escape(str(replay_of))}</p>")
    if not s.scan.complete:
        banner += (f'<p class="warn">Incomplete recording: '
                   f"{html.escape(str(s.scan.stopped_at))}</p>")
    for note in s.scan.notes:
        banner += f'<p class="warn">{html.escape(note)}</p>'
    if s.config is None:
        banner += (f'<p class="warn">The configuration of this run is unknown: '
                   f"{html.escape(s.config_problem)}; the defaults were used for the "
                   f"human-body filter, the force limit and the force-loop numbers.</p>")
    if not s.tick.size:
        banner += '<p class="warn">The recording holds no tick records.</p>'

    # the bars and the events first (what a person looks for on the first screen: the
    # table of numbers is long and grows with what the controller estimates)
    summary = numbers = ""
    if phases:
        glance = _figure(by_name["summary.png"]) if "summary.png" in by_name else ""
        summary = f'<section id="summary"><h2>Passive vs active</h2>{glance}</section>'
        numbers = (f'<section id="numbers"><h2>Passive vs active, the numbers</h2>'
                   f"{_summary_table(phases)}</section>")
    sections = []
    for heading, names in _SECTIONS:
        figs = "".join(_figure(by_name[n]) for n in names if n in by_name)
        if figs:
            sections.append(f"<section><h2>{html.escape(heading)}</h2>{figs}</section>")
    run_rows = "".join(f'<tr><th>{html.escape(k)}</th><td class="num">{fmt_num(v)}</td></tr>'
                       for k, v in metrics.items())
    meta_rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v[:200])}</td></tr>"
                        for k, v in sorted(meta.items()) if k != "versions")
    name = html.escape(Path(path).name)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>Run report {name}</title>
<style>{_css()}</style></head>
<body data-images-loaded="pending">
<h1>Run report: {name}</h1>
<p class="lede">{_run_facts(s, metrics)}</p>
{banner}
{_phase_key(s)}
{summary}
<section id="events"><h2>Events</h2>
{_events_table(events)}</section>
{numbers}
{"".join(sections)}
<section id="run"><h2>Whole run</h2><table>{run_rows}</table></section>
<details><summary>Recording metadata</summary><table>{meta_rows}</table></details>
{_SCRIPT}
</body></html>
"""
    (out / "index.html").write_text(page, encoding="utf-8")
