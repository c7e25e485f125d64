"""What each issue-11 change buys: every change turned off alone on the current tree.

    python -m hil.study.changes [--jobs N] [--quick] [--config F]

Each row runs the same runs twice, with the change (the configuration as given) and
without it (only that change undone), and prints one markdown table for docs/study.md.
The runs are those of the commands in the issue's "Must show" list:

- ``mcS ctrl``: ``rig montecarlo --runs 20 --spread S --duration 20 --weights 1
  --controller ctrl`` (rough course, 25 mph, seed 1; faulted runs, bump-stop slams, mean
  absorbed power over the plants);
- ``course``: ``rig sim --road rough-course --duration D --seed s`` for seeds 1-3 (ratio
  of absorbed power to passive, faults, share of ticks the estimator monitor had the
  bank degraded);
- ``30 s``: ``rig sim --duration 30 --seed 1`` (ratio to passive).

Where a change is not a configuration key the row says how it is undone: the old
divergence rule (min q > 1e4 for 50 ticks, latched) is evaluated on the recorded q of
the same runs; the old ride height is ``--own-ride-height``; the old skyhook is its
gains and LVDT-rate low-pass before the retune.  ``--quick`` shortens every run and the
Monte Carlo to 4 plants (for the test suite; the numbers are then not the study's).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import RigConfig, config_to_toml, default_config, load_config
from hil.batch import BatchExecutor, LocalExecutor
from hil.sim.closed_loop import (
    BankController,
    cached_design,
    config_from_text,
    run_closed_loop,
    simulate,
)
from hil.sim.montecarlo import RIDE_HEIGHT_STD_M, draw_params
from hil.sim.roads import make_road
from hil.sim.skyhook import DEFAULT_GAINS, SkyhookController, SkyhookGains

__all__ = ["CHANGES", "OLD_SKYHOOK", "Change", "Run", "main", "measure", "old_divergence_rule"]

THESIS_SPEED_MPS = 11.176
#: the thesis-literal estimation and blending profile
THESIS_PROFILE = str(Path(__file__).resolve().parents[2] / "deploy" / "thesis.toml")
#: the skyhook before the retune for the flow feedforward (gains and LVDT-rate low-pass)
OLD_SKYHOOK = SkyhookGains(2000.0, 0.0, 0.5, rattle_rate_lowpass_hz=40.0)
#: the divergence test the estimator monitor replaced: min q above this ...
OLD_DIVERGENCE_Q = 1e4
#: ... for this many consecutive ticks latched ESTIMATOR_DIVERGED
OLD_DIVERGENCE_TICKS = 50


@dataclass(frozen=True)
class Run:
    """One closed-loop run (picklable): ``overrides`` {section: {key: value}} on the
    configuration (or on ``profile``, a configuration file); ``mc`` = (spread, plant
    index, runs, ride-height std or None) draws the plant like ``rig montecarlo --seed
    1``; ``skyhook`` replaces the default gains."""

    controller: str
    weight_set: int = 1
    duration_s: float = 30.0
    seed: int = 1
    overrides: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = ()
    mc: tuple[float, int, int, float | None] | None = None
    skyhook: SkyhookGains | None = None
    record: bool = False
    profile: str | None = None          # a configuration file instead of the given one


def _config(base: RigConfig, run: Run) -> RigConfig:
    cfg = load_config(run.profile) if run.profile is not None else base
    for section, items in run.overrides:
        cfg = cfg.replace(**{section: dict(items)})
    return cfg


def old_divergence_rule(q: np.ndarray) -> bool:
    """Would the removed test have latched DIVERGED?  ``q`` (ticks, models) as recorded by
    :func:`hil.sim.closed_loop.run_closed_loop` (0 for a filter not running): min over the running
    filters above :data:`OLD_DIVERGENCE_Q` for :data:`OLD_DIVERGENCE_TICKS` ticks."""
    running = np.where(q > 0.0, q, np.inf)
    over = np.min(running, axis=1) > OLD_DIVERGENCE_Q
    over &= np.isfinite(np.min(running, axis=1))
    streak = 0
    for o in over:
        streak = streak + 1 if o else 0
        if streak >= OLD_DIVERGENCE_TICKS:
            return True
    return False


def _one(config_toml: str, run: Run) -> dict[str, float]:
    cfg = _config(config_from_text(config_toml), run)
    road = make_road("rough-course", THESIS_SPEED_MPS, run.duration_s, cfg.sample_time_s,
                     run.seed)
    params, sim_seed = None, run.seed
    if run.mc is not None:
        spread, i, n, rh = run.mc
        params = draw_params(cfg, n, spread, run.seed, rh)[i]
        sim_seed = run.seed + 1000 + i
    if run.controller == "skyhook" or (run.record and run.controller != "passive"):
        ctrl: Any = (SkyhookController(cfg, run.skyhook or DEFAULT_GAINS)
                     if run.controller == "skyhook"
                     else BankController(cached_design(cfg), cfg, run.controller,
                                         run.weight_set, road))
        res = run_closed_loop(cfg, road, ctrl, seed=sim_seed, params=params,
                              record_weights=run.record)
    else:
        res = simulate(cfg, road, run.controller, run.weight_set, seed=sim_seed,
                       params=params)
    m = {k: float(v) for k, v in res.metrics.items()}
    if run.record and "q" in res.traces:
        m["old_rule_latched"] = float(old_divergence_rule(res.traces["q"]))
        off = res.traces["off_ground_s"] > 0.0
        w = res.traces["firing_weight"]
        m["airborne_weight_in_flight"] = float(w[off, -1].mean()) if off.any() else math.nan
        m["airborne_weight_on_ground"] = float(w[~off, -1].mean())
    return m


Cell = Callable[[list[dict[str, float]], list[Run]], str]


@dataclass
class Change:
    """A row: ``name``, what is measured (``runs`` -> the runs with the change) and how a
    cell is written (``cell`` of the runs' metrics; ``cell_without`` for the runs without
    the change, if they are to be read differently).  Undone by ``undo`` (configuration
    overrides on top of the run's) or ``without`` (a function that rewrites each run)."""

    name: str
    measured: str
    runs: Callable[[bool], list[Run]]
    cell: Cell
    undo: dict[str, dict[str, Any]] = field(default_factory=dict)
    without: Callable[[Run], Run] | None = None
    cell_without: Cell | None = None
    undone_by: str = ""


def _ov(d: dict[str, dict[str, Any]]) -> tuple[tuple[str, tuple[tuple[str, Any], ...]], ...]:
    return tuple((s, tuple(sorted(kv.items()))) for s, kv in sorted(d.items()))


def _mc_runs(controllers: Sequence[str], spread: float, quick: bool,
             rh: float | None = RIDE_HEIGHT_STD_M, record: bool = False) -> list[Run]:
    n, dur = (4, 3.0) if quick else (20, 20.0)
    return [Run(c, 1, dur, 1, mc=(spread, i, n, rh), record=record)
            for c in controllers for i in range(n)]


def _course_runs(controllers: Sequence[str], ws: int, quick: bool,
                 record: bool = False) -> list[Run]:
    dur, seeds = (3.0, (1,)) if quick else (60.0, (1, 2, 3))
    return [Run(c, ws, dur, s, record=record) for c in ("passive", *controllers)
            for s in seeds]


def _by(ms: list[dict[str, float]], runs: list[Run], ctrl: str) -> list[dict[str, float]]:
    return [m for m, r in zip(ms, runs, strict=True) if r.controller == ctrl]


def _mc_cell(ctrls: Sequence[str]) -> Cell:
    def cell(ms: list[dict[str, float]], runs: list[Run]) -> str:
        parts = []
        for c in ctrls:
            sel = _by(ms, runs, c)
            faults = sum(m["n_faults"] > 0 for m in sel)
            slams = sum(m["bump_stop_slam"] > 0 for m in sel)
            ap = np.mean([m["absorbed_power"] for m in sel])
            parts.append(f"{c}: {faults} faulted, {slams} slams, mean {ap:.4f}")
        return "; ".join(parts)
    return cell


def _course_cell(ctrls: Sequence[str], extra: str = "") -> Cell:
    def cell(ms: list[dict[str, float]], runs: list[Run]) -> str:
        passive = {r.seed: m["absorbed_power"] for m, r in zip(ms, runs, strict=True)
                   if r.controller == "passive"}
        parts = []
        for c in ctrls:
            pairs = [(m, r) for m, r in zip(ms, runs, strict=True) if r.controller == c]
            ratios = [m["absorbed_power"] / passive[r.seed] for m, r in pairs]
            faults = sum(m["n_faults"] > 0 for m, _ in pairs)
            deg = np.mean([m.get("degraded_fraction", 0.0) for m, _ in pairs])
            text = (f"{c}: {'/'.join(f'{x:.3f}' for x in ratios)} x passive, "
                    f"{faults} faulted, degraded {100 * deg:.2f} %")
            if extra == "airborne":
                w = np.nanmean([m["airborne_weight_in_flight"] for m, _ in pairs])
                g = np.mean([m["airborne_weight_on_ground"] for m, _ in pairs])
                text += f", airborne weight {w:.2f} in flight / {g:.3f} on ground"
            parts.append(text)
        return "; ".join(parts)
    return cell


def _ratio_cell(ctrls: Sequence[str]) -> Cell:
    def cell(ms: list[dict[str, float]], runs: list[Run]) -> str:
        p = _by(ms, runs, "passive")[0]["absorbed_power"]
        return ", ".join(f"{c} {_by(ms, runs, c)[0]['absorbed_power'] / p:.3f}"
                         for c in ctrls)
    return cell


def _old_rule_cell(ctrls: Sequence[str]) -> Cell:
    course = _course_cell(ctrls)

    def cell(ms: list[dict[str, float]], runs: list[Run]) -> str:
        old = []
        for c in ctrls:
            sel = _by(ms, runs, c)
            n = sum(m.get("old_rule_latched", 0.0) > 0 for m in sel)
            old.append(f"{c} {n} of {len(sel)}")
        return (course(ms, runs) + "; the removed rule latches DIVERGED (then passive) in "
                + ", ".join(old))
    return cell


def _fuzzy_vs_lqg(ms: list[dict[str, float]], runs: list[Run]) -> str:
    f = np.mean([m["absorbed_power"] for m in _by(ms, runs, "fuzzy")])
    lq = np.mean([m["absorbed_power"] for m in _by(ms, runs, "lqg")])
    nr = np.mean([m.get("no_rule_fired_fraction", 0.0) for m in _by(ms, runs, "fuzzy")])
    return f"fuzzy / lqg {f / lq:.2f}, no rule fired {100 * nr:.0f} % of ticks"


def _ride_height_off(run: Run) -> Run:
    assert run.mc is not None
    return replace(run, mc=(run.mc[0], run.mc[1], run.mc[2], None))


def _old_skyhook(run: Run) -> Run:
    return replace(run, skyhook=OLD_SKYHOOK) if run.controller == "skyhook" else run


def _sim30(ctrls: Sequence[str]) -> Callable[[bool], list[Run]]:
    return lambda quick: [Run(c, 1, 3.0 if quick else 30.0, 1)
                          for c in ("passive", *ctrls)]


CHANGES: list[Change] = [
    Change("bump-stop force as a known filter input",
           "rough course 60 s, seeds 1-3, weight set 2",
           lambda q: _course_runs(("lqg", "fuzzy"), 2, q), _course_cell(("lqg", "fuzzy")),
           undo={"design": {"bump_stop_filter_input": False}}),
    Change("rattlespace-bias state + accelerometer mean removal",
           "Monte Carlo 15 %, 20 plants",
           lambda q: _mc_runs(("lqg",), 0.15, q), _mc_cell(("lqg",)),
           undo={"design": {"filter_rattlespace_bias_drift": 0.0,
                            "accel_mean_window_s": 0.0}}),
    Change("chi-square estimator monitor (degrade / re-arm; latch only when unusable)",
           "thesis profile (deploy/thesis.toml), rough course 60 s, seeds 1-3, weight set 2",
           lambda q: [replace(r, profile=THESIS_PROFILE, record=True)
                      for r in _course_runs(("lqg", "fuzzy"), 2, q)],
           _course_cell(("lqg", "fuzzy")), cell_without=_old_rule_cell(("lqg", "fuzzy")),
           undo={"safety": {"estimator_nis_inflation": 1e9}},
           undone_by="the monitor never degrades; the removed rule, min q > 1e4 for 50 "
                     "ticks, evaluated on those runs' q"),
    Change("fuzzy on the windowed q relative to the best model (+ best-model fallback)",
           "Monte Carlo 5 %, 20 plants", lambda q: _mc_runs(("lqg", "fuzzy"), 0.05, q),
           _fuzzy_vs_lqg, undo={"fuzzy": {"statistic": "raw",
                                          "no_fire_fallback": "passive"}}),
    Change("airborne filter with wheel-force noise",
           "rough course 60 s, seeds 1-3, Bayes weight set 1",
           lambda q: _course_runs(("bayes",), 1, q, record=True),
           _course_cell(("bayes",), "airborne"),
           undo={"design": {"airborne_filter_wheel_force_intensity": 0.0}}),
    Change("Monte Carlo ride height set by preload",
           "Monte Carlo 15 %, 20 plants",
           lambda q: _mc_runs(("passive", "lqg"), 0.15, q), _mc_cell(("passive", "lqg")),
           without=_ride_height_off, undone_by="--own-ride-height"),
    Change("valve flow feedforward + LQ gains for it",
           "rough course 30 s, seed 1, ratio to passive",
           _sim30(("zero-force", "lqg", "fuzzy")), _ratio_cell(("zero-force", "lqg", "fuzzy")),
           undo={"force_loop": {"flow_feedforward_gain": 0.0}}),
    Change("skyhook retuned for the feedforward",
           "rough course 30 s, seed 1, ratio to passive",
           _sim30(("skyhook",)), _ratio_cell(("skyhook",)), without=_old_skyhook,
           undone_by="gains 2000 / 0 / 0.5, LVDT-rate low-pass 40 Hz"),
    Change("end-stop guard", "Monte Carlo 15 %, 20 plants",
           lambda q: _mc_runs(("lqg", "fuzzy"), 0.15, q), _mc_cell(("lqg", "fuzzy")),
           undo={"design": {"stop_guard_m": 0.0}}),
]


def measure(cfg: RigConfig, changes: Sequence[Change] = tuple(CHANGES), *,
            quick: bool = False, jobs: int | None = None,
            executor: BatchExecutor | None = None) -> list[tuple[str, str, str, str]]:
    """(change, measured on, with it, without it) per change."""
    plan: list[tuple[int, int, Run]] = []
    for ci, ch in enumerate(changes):
        for r in ch.runs(quick):
            plan.append((ci, 1, r))
            off = ch.without(r) if ch.without is not None else replace(
                r, overrides=_ov({**dict((s, dict(kv)) for s, kv in r.overrides),
                                  **ch.undo}))
            plan.append((ci, 0, off))
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(plan)))
    ex = executor if executor is not None else LocalExecutor(jobs)
    try:
        metrics = ex.run(_one, config_to_toml(cfg), [r for _, _, r in plan],
                         [f"{changes[c].name} ({'with' if v else 'without'}): {r}"
                          for c, v, r in plan], desc="changes").values()
    finally:
        if executor is None:
            ex.close()
    out = []
    for ci, ch in enumerate(changes):
        cells = []
        for variant in (1, 0):
            sel = [(m, r) for (c, v, r), m in zip(plan, metrics, strict=True)
                   if c == ci and v == variant]
            cell = ch.cell if variant == 1 or ch.cell_without is None else ch.cell_without
            cells.append(cell([m for m, _ in sel], [r for _, r in sel]))
        measured = ch.measured + (f" (without: {ch.undone_by})" if ch.undone_by else "")
        out.append((ch.name, measured, cells[0], cells[1]))
    return out


def table(rows: Sequence[tuple[str, str, str, str]]) -> str:
    lines = ["| change | measured on | with it | without it |", "|---|---|---|---|"]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hil.study.changes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="configuration file (default: built-in)")
    p.add_argument("--jobs", type=int, default=None, help="worker processes")
    p.add_argument("--quick", action="store_true", help="short runs, 4 plants (tests)")
    args = p.parse_args(argv)
    cfg = load_config(args.config) if args.config else default_config()
    print(table(measure(cfg, quick=args.quick, jobs=args.jobs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
