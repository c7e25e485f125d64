"""HTML run report with PNG plots (matplotlib Agg) of a recording (``docs/replay.md``).

``write_report(run.mcap, out_dir)`` writes ``out_dir/index.html`` and one PNG per plot:
rattlespace, sprung acceleration, force command vs measured force, firing weight and
likelihood quotient q per model, lifecycle and faults over time, loop timing histogram,
and a metrics table (absorbed power proxy: mean square of the measured sprung
acceleration through the thesis's human-body filter F(s) of the configuration, ISO 2631
Wk RMS, rattlespace RMS / peak, force tracking, lateness percentiles ...; filters from
``hil.metrics``).  A recording written by ``rig replay --out`` is marked open loop and,
when its source recording is still there, compared with it.

The page carries a small inline script that sets ``data-images-loaded="n/m"`` on
``<body>`` once every image has loaded (tests check it in headless Chromium).
"""

from __future__ import annotations

import html
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rig.mcap_schema import TOPIC_EVENTS, TOPIC_INTERNALS, TOPIC_SIGNALS, TOPIC_TIMING
from rig.protocol import LifecycleState
from rig.recording import CONFIG_ATTACHMENT, DESIGN_ATTACHMENT
from rig.replay import OPEN_LOOP_NOTE, RecordingError, ScanResult, scan_recording, split_json

__all__ = ["RunSeries", "load_series", "run_metrics", "write_report"]

FloatArray = NDArray[np.float64]
#: longest series drawn point by point; longer ones are drawn as a min/max envelope
MAX_PLOT_POINTS = 20_000
_STATES = [s.name for s in LifecycleState]


@dataclass
class RunSeries:
    """Per-tick series of a recording (NaN where a value was not recorded)."""

    path: Path
    scan: ScanResult
    tick: NDArray[np.int64]
    t_s: FloatArray                       # seconds since the first tick
    signals: dict[str, FloatArray]
    lifecycle: list[str]
    fault: list[str | None]
    per_model: dict[str, FloatArray]      # (n, J): q, firing_weight, probability, u_model
    timing: dict[str, FloatArray]
    events: list[dict[str, Any]]
    model_names: list[str] = field(default_factory=list)

    @property
    def dt_s(self) -> float:
        d = np.diff(self.t_s)
        return float(np.median(d)) if d.size else 1e-3


def _f(v: Any) -> float:
    """A recorded number; NaN for null or anything that is not a number."""
    return float(v) if isinstance(v, int | float) else math.nan


def _matrix(rows: list[Any], width: int) -> FloatArray:
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        if isinstance(r, list) and r:
            k = min(width, len(r))
            out[i, :k] = [_f(x) for x in r[:k]]
    return out


def _objects(path: str | Path, topic: str, joined: bytes,
             seqs: list[int]) -> list[dict[str, Any]]:
    """The JSON objects of a topic's payloads; RecordingError naming the first that is
    not one."""
    try:
        objs = split_json(joined)
    except (ValueError, RecursionError) as exc:   # JSONDecodeError, UnicodeDecodeError
        raise RecordingError(f"{path}: a {topic} payload is not JSON "
                             f"({type(exc).__name__}: {str(exc)[:120]})") from None
    if len(objs) != len(seqs):
        raise RecordingError(f"{path}: {len(seqs)} {topic} messages hold {len(objs)} JSON "
                             "values, expected one object each")
    for i, obj in enumerate(objs):
        if not isinstance(obj, dict):
            raise RecordingError(f"{path}: {topic} message {_which(i, seqs)} is a JSON "
                                 f"{type(obj).__name__}, expected an object")
    return objs


def _which(i: int, seqs: list[int]) -> str:
    return f"{i} (sequence {seqs[i]})" if i < len(seqs) else str(i)


def _require_int(path: str | Path, topic: str, objs: list[dict[str, Any]], seqs: list[int],
                 *keys: str) -> None:
    for i, obj in enumerate(objs):
        for key in keys:
            v = obj.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or not -(1 << 63) <= v < 1 << 63:
                what = "has no" if key not in obj else \
                    f"has {key} = {str(v)[:40]!r}, not a 64-bit"
                raise RecordingError(f"{path}: {topic} message {_which(i, seqs)} {what} "
                                     f"integer '{key}'")


def load_series(path: str | Path) -> RunSeries:
    """Decode signals, internals, timing and events of a recording (errors: see
    :func:`rig.replay.scan_recording`)."""
    parts: dict[str, list[tuple[bytes, NDArray[np.uint32]]]] = {
        TOPIC_SIGNALS: [], TOPIC_INTERNALS: [], TOPIC_TIMING: [], TOPIC_EVENTS: []}

    def collector(topic: str) -> Any:
        return lambda joined, seqs: parts[topic].append((joined, seqs))

    scan = scan_recording(path, {t: collector(t) for t in parts})

    def decoded(topic: str) -> tuple[list[dict[str, Any]], list[int]]:
        seqs = [int(q) for _, s in parts[topic] for q in s]
        return _objects(path, topic, b"".join(j for j, _ in parts[topic]), seqs), seqs

    recs, rec_seqs = decoded(TOPIC_SIGNALS)
    where = {q: i for i, q in enumerate(rec_seqs)}
    for topic in (TOPIC_INTERNALS, TOPIC_TIMING):  # parts of the same tick record
        for obj, q in zip(*decoded(topic), strict=True):
            i = where.get(q)
            if i is not None:
                recs[i].update(obj)
    _require_int(path, TOPIC_SIGNALS, recs, rec_seqs, "tick", "t_ns")
    events, event_seqs = decoded(TOPIC_EVENTS)
    _require_int(path, TOPIC_EVENTS, events, event_seqs, "tick")
    n = len(recs)
    tick = np.array([r["tick"] for r in recs], dtype=np.int64)
    t_ns = np.array([r["t_ns"] for r in recs], dtype=np.int64)
    t_s = (t_ns - t_ns[0]) * 1e-9 if n else np.zeros(0)
    sig_keys = ("rattlespace_m", "sprung_accel_mps2", "force_meas_n", "force_ref_n",
                "spool_cmd", "valve_enable")
    signals = {k: np.array([_f(r.get(k)) for r in recs]) for k in sig_keys}
    timing = {k: np.array([_f(r.get(k)) for r in recs])
              for k in ("wake_late_s", "compute_s", "period_s")}
    J = max((len(qs) for r in recs if isinstance(qs := r.get("q"), list)), default=0)
    per_model = {k: _matrix([r.get(k) for r in recs], J)
                 for k in ("q", "firing_weight", "probability", "u_model")}
    names = _model_names(scan, J)
    return RunSeries(Path(path), scan, tick, t_s, signals,
                     [str(r.get("lifecycle", "")) for r in recs],
                     [r.get("fault") for r in recs], per_model, timing, events, names)


def _model_names(scan: ScanResult, J: int) -> list[str]:
    raw = scan.rig_metadata.get("models")
    try:
        names = [str(x) for x in json.loads(raw)] if raw else []
    except (json.JSONDecodeError, TypeError):
        names = []
    if len(names) != J and DESIGN_ATTACHMENT in scan.attachments:
        import io

        try:
            with np.load(io.BytesIO(scan.attachments[DESIGN_ATTACHMENT])) as npz:
                names = [str(x) for x in npz["model_names"]]
        except (OSError, ValueError, KeyError):
            names = []
    return names if len(names) == J else [f"model {j}" for j in range(J)]


# ---------------------------------------------------------------------------- metrics


def _rms(x: FloatArray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def _human_filter(scan: ScanResult) -> tuple[list[float], list[float]]:
    raw = scan.attachments.get(CONFIG_ATTACHMENT)
    if raw is not None:
        try:
            d = tomllib.loads(raw.decode()).get("design", {})
            return list(d["human_filter_num"]), list(d["human_filter_den"])
        except (tomllib.TOMLDecodeError, UnicodeDecodeError, KeyError, TypeError):
            pass
    return [12.0, 0.0], [1.0, 30.02, 901.3]


def run_metrics(s: RunSeries) -> dict[str, float | int | str]:
    """Summary metrics of the measured signals (independent of the controller's view)."""
    from hil.metrics import filter_signal, wk_tf

    dt = s.dt_s
    acc = np.nan_to_num(s.signals["sprung_accel_mps2"])
    rs = s.signals["rattlespace_m"]
    active = s.signals["valve_enable"] > 0
    num, den = _human_filter(s.scan)
    acc_f = filter_signal(acc, np.asarray(num), np.asarray(den), dt) if acc.size else acc
    wn, wd = wk_tf()
    acc_wk = filter_signal(acc, wn, wd, dt) if acc.size else acc
    err = (s.signals["force_ref_n"] - s.signals["force_meas_n"])[active]
    late = s.timing["wake_late_s"] * 1e6
    late = late[np.isfinite(late)]
    comp = s.timing["compute_s"] * 1e6
    comp = comp[np.isfinite(comp)]
    faults = [e for e in s.events if e.get("kind") == "fault"]

    def pct(x: FloatArray, q: float) -> float:
        return float(np.percentile(x, q)) if x.size else math.nan

    return {
        "duration_s": float(s.t_s[-1] + dt) if s.t_s.size else 0.0,
        "ticks": int(s.tick.size),
        "time_active_s": float(active.sum() * dt),
        "accel_rms_mps2": _rms(acc),
        "absorbed_power_proxy": float(np.mean(acc_f * acc_f)) if acc.size else math.nan,
        "wk_rms_mps2": _rms(acc_wk),
        "rattlespace_rms_mm": 1e3 * _rms(rs),
        "rattlespace_peak_mm": 1e3 * float(np.nanmax(np.abs(rs))) if rs.size else math.nan,
        "force_meas_rms_n": _rms(s.signals["force_meas_n"]),
        "force_tracking_rms_error_n (active)": _rms(err),
        "lateness_p50_us": pct(late, 50), "lateness_p99_us": pct(late, 99),
        "lateness_max_us": float(late.max()) if late.size else math.nan,
        "compute_p99_us": pct(comp, 99),
        "faults": len(faults),
        "recording": "complete" if s.scan.complete else f"incomplete: {s.scan.stopped_at}",
    }


# ---------------------------------------------------------------------------- plots


def _envelope(t: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(t, lo, hi): min/max per bucket when longer than MAX_PLOT_POINTS, else (t, y, y)."""
    n = y.shape[0]
    if n <= MAX_PLOT_POINTS:
        return t, y, y
    b = math.ceil(n / (MAX_PLOT_POINTS // 2))
    m = n // b
    yy = y[: m * b].reshape(m, b)
    with np.errstate(all="ignore"):
        return t[: m * b: b], np.nanmin(yy, axis=1), np.nanmax(yy, axis=1)


def _line(ax: Any, t: FloatArray, y: FloatArray, **kw: Any) -> None:
    tt, lo, hi = _envelope(t, y)
    if lo is hi:
        ax.plot(tt, lo, lw=0.8, **kw)
    else:
        color = kw.pop("color", None)
        poly = ax.fill_between(tt, lo, hi, alpha=0.7, lw=0.6, color=color, **kw)
        poly.set_edgecolor(poly.get_facecolor())


def _shade_active(ax: Any, s: RunSeries) -> None:
    on = s.signals["valve_enable"] > 0
    if not on.any():
        return
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0]))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        ax.axvspan(s.t_s[a], s.t_s[b - 1], color="tab:green", alpha=0.08, lw=0)


def _plots(s: RunSeries, out: Path, compare: RunSeries | None) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = s.t_s
    made: list[tuple[str, str]] = []

    def save(fig: Any, name: str, title: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        made.append((name, title))

    fig, ax = plt.subplots(figsize=(10, 3))
    _shade_active(ax, s)
    _line(ax, t, 1e3 * s.signals["rattlespace_m"], color="tab:blue")
    ax.set(xlabel="time [s]", ylabel="rattlespace [mm]",
           title="Rattlespace about static (compression +); green = controller active")
    save(fig, "rattlespace.png", "Rattlespace")

    fig, ax = plt.subplots(figsize=(10, 3))
    _shade_active(ax, s)
    _line(ax, t, s.signals["sprung_accel_mps2"], color="tab:purple")
    ax.set(xlabel="time [s]", ylabel="sprung accel [m/s²]",
           title="Sprung-mass acceleration (gravity removed, up +)")
    save(fig, "acceleration.png", "Accelerations")

    fig, ax = plt.subplots(figsize=(10, 3.2))
    _shade_active(ax, s)
    _line(ax, t, 1e-3 * s.signals["force_ref_n"], color="tab:red", label="force command")
    _line(ax, t, 1e-3 * s.signals["force_meas_n"], color="tab:gray", label="measured (load cell)")
    ax.set(xlabel="time [s]", ylabel="force [kN]", title="Force command vs measured force")
    ax.legend(loc="upper right", fontsize=8)
    save(fig, "force.png", "Force command vs measured force")

    J = s.per_model["q"].shape[1]
    fig, axs = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    for j in range(J):
        name = s.model_names[j] if j < len(s.model_names) else f"model {j}"
        _line(axs[0], t, s.per_model["firing_weight"][:, j], label=name)
        _line(axs[1], t, s.per_model["q"][:, j], label=name)
    axs[0].set(ylabel="firing weight", title="Firing weight and likelihood quotient q per model")
    axs[1].set(xlabel="time [s]", ylabel="q")
    if J:
        axs[1].set_yscale("symlog", linthresh=1.0)
        axs[0].legend(loc="upper right", fontsize=7, ncol=min(J, 4))
    save(fig, "models.png", "Firing weights and q per model")

    fig, ax = plt.subplots(figsize=(10, 2.6))
    code = np.array([_STATES.index(x) if x in _STATES else -1 for x in s.lifecycle])
    ax.step(t, code, where="post", color="tab:blue")
    ax.set_yticks(range(len(_STATES)), _STATES)
    ax.set_ylim(-0.5, len(_STATES) - 0.5)
    t0 = int(s.tick[0]) if s.tick.size else 0
    for e in s.events:
        if e.get("kind") == "fault" and isinstance(e.get("detail"), dict):
            x = (int(e["tick"]) - t0) * s.dt_s
            ax.axvline(x, color="tab:red", lw=1)
            ax.annotate(str(e["detail"].get("fault", "fault")), (x, 2), fontsize=7,
                        color="tab:red", rotation=90, va="bottom")
    ax.set(xlabel="time [s]", title="Lifecycle and faults")
    save(fig, "lifecycle.png", "Lifecycle and faults over time")

    fig, ax = plt.subplots(figsize=(10, 3))
    for key, label in (("wake_late_s", "wake-up lateness"), ("compute_s", "compute time")):
        us = s.timing[key] * 1e6
        us = us[np.isfinite(us)]
        if us.size:
            ax.hist(us, bins=100, alpha=0.6, label=label)
    ax.set_yscale("log")
    ax.set(xlabel="µs", ylabel="ticks", title="Loop timing")
    ax.legend(fontsize=8)
    save(fig, "timing.png", "Loop timing histogram")

    if compare is not None:
        fig, ax = plt.subplots(figsize=(10, 3.2))
        k = np.intersect1d(s.tick, compare.tick)
        a = np.searchsorted(compare.tick, k)
        b = np.searchsorted(s.tick, k)
        tt = (k - k[0]) * s.dt_s if k.size else np.zeros(0)
        _line(ax, tt, 1e-3 * compare.signals["force_ref_n"][a], color="tab:gray",
              label="recorded controller")
        _line(ax, tt, 1e-3 * s.signals["force_ref_n"][b], color="tab:red",
              label="replayed controller")
        ax.set(xlabel="time [s]", ylabel="force reference [kN]",
               title="Same sensor data, two controllers (open loop)")
        ax.legend(fontsize=8)
        save(fig, "comparison.png", "Recorded vs replayed controller (open loop)")
    return made


# ---------------------------------------------------------------------------- HTML

_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
  }
  document.body.setAttribute('data-images-loaded', ok + '/' + imgs.length);
});
</script>"""


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "–" if math.isnan(v) else f"{v:.4g}"
    return html.escape(str(v))


def write_report(path: str | Path, out_dir: str | Path | None = None,
                 compare: str | Path | None = None) -> Path:
    """Write the report of recording ``path`` into ``out_dir`` (default: next to the
    recording, ``<stem>-report/``); returns the HTML file.  ``compare`` (default: the
    source of a replay, if it exists) adds the side-by-side controller plot."""
    s = load_series(path)
    out = Path(out_dir) if out_dir is not None else Path(path).with_name(
        f"{Path(path).stem}-report")
    out.mkdir(parents=True, exist_ok=True)
    meta = s.scan.rig_metadata
    replay_of = meta.get("replay_of")
    open_loop = meta.get("open_loop") == "true"
    if compare is None and replay_of and open_loop and Path(replay_of).exists():
        compare = replay_of
    other = load_series(compare) if compare is not None else None
    plots = _plots(s, out, other) if s.tick.size else []
    metrics = run_metrics(s) if s.tick.size else {}
    rows = "\n".join(f"<tr><th>{html.escape(k)}</th><td>{_fmt(v)}</td></tr>"
                     for k, v in metrics.items())
    meta_rows = "\n".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v[:200])}</td></tr>"
                          for k, v in sorted(meta.items()) if k != "versions")
    banner = ""
    if open_loop:
        banner += f'<p class="warn"><b>Replay, {html.escape(OPEN_LOOP_NOTE)}.</b> '
        banner += f"Source: {html.escape(str(replay_of))}</p>"
    if not s.scan.complete:
        banner += (f'<p class="warn">Incomplete recording: '
                   f"{html.escape(str(s.scan.stopped_at))}</p>")
    for note in s.scan.notes:
        banner += f'<p class="warn">{html.escape(note)}</p>'
    faults = "".join(
        f"<li>tick {e['tick']}: {html.escape(json.dumps(e.get('detail')))[:300]}</li>"
        for e in s.events if e.get("kind") in ("fault", "lifecycle", "command"))
    figs = "\n".join(f'<figure><img src="{n}" alt="{html.escape(title)}">'
                     f"<figcaption>{html.escape(title)}</figcaption></figure>"
                     for n, title in plots)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>Run report {html.escape(Path(path).name)}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1000px; }}
table {{ border-collapse: collapse; margin-bottom: 1em; }}
th, td {{ border: 1px solid #ccc; padding: 2px 8px; text-align: left; font-size: 90%; }}
.warn {{ background: #fff3cd; padding: 0.5em; border: 1px solid #e0c060; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; }}
</style></head>
<body data-images-loaded="pending">
<h1>Run report: {html.escape(Path(path).name)}</h1>
{banner}
<h2>Summary metrics</h2>
<table>{rows}</table>
{figs}
<h2>Events</h2>
<ul>{faults or "<li>none</li>"}</ul>
<h2>Recording metadata</h2>
<table>{meta_rows}</table>
{_SCRIPT}
</body></html>
"""
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    return index
