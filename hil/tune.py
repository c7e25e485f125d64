"""``rig tune``: search the LQ weights (and the force-loop / fuzzy settings that matter)
for the least absorbed power over a Monte Carlo set of plants and roads, under the
constraints a rig engineer sets.

Each trial is a configuration: the Eq. 2.5 weights rho1, rho2, rho3 (rho4 = 1; only the
ratios matter) searched log-uniformly over :data:`SEARCH_SPACE`, the valve flow
feedforward gain and the PI force loop's proportional gain, and (for the ``relative``
fuzzy statistic) the fuzzy window.  Every trial runs the same set: ``plants`` plants
drawn like ``rig montecarlo`` (:func:`hil.sim.montecarlo.draw_params`, ``spread``,
``seed``) on every road of ``roads``, each run a :func:`hil.sim.closed_loop.simulate`
call through the batch seam (:mod:`hil.batch`: local pool or ``--cluster``).  Every run
is compared with the passive run of the same plant and road:

* objective (minimised): mean over the runs of absorbed power / passive absorbed power;
* constraints (optuna ``Trial.set_constraint``, which replaced the sampler's
  ``constraints_func`` in optuna 5; feasible when every value is <= 0): mean
  rattlespace RMS ratio <= the rattlespace bound, mean dynamic tire-load RMS ratio <= the
  tire-load bound, no run with a latched fault (or a non-finite plant), no bump-stop
  slam.  A bound is a ratio to passive (1 = passive) or ``baseline``: the value of the
  configuration's own weight set 1 (the thesis set) on the same plants and roads.

The search is optuna's TPE sampler (seeded) in a :class:`optuna.storages.JournalStorage`
on a file in the output directory, so a search stopped at any point is resumed by
running the same command again (``--trials`` is the total).  The configuration's own
weight set 1 is the first trial, so the search starts from the thesis set.  Output:
``tuned.toml`` (the configuration with the best feasible trial as weight set 1 and its
settings; the earlier sets follow), ``pareto.png`` (absorbed power vs rattlespace vs
tire load of every trial), ``tune.json``.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import RigConfig, config_hash, config_to_toml
from hil.batch import BatchExecutor
from hil.sim.closed_loop import config_from_text, simulate
from hil.sim.montecarlo import draw_params
from hil.sim.plant import PlantParams
from hil.sim.roads import Road, make_road

__all__ = ["JOURNAL", "SEARCH_SPACE", "TuneError", "TunePlan", "TuneResult", "run_tune",
           "trial_config"]

#: the searched keys: (name, config section, key, low, high, log scale)
SEARCH_SPACE: tuple[tuple[str, str, str, float, float, bool], ...] = (
    ("rho1", "design", "rho1", 1e-2, 1e4, True),        # tire deflection weight
    ("rho2", "design", "rho2", 1e-3, 1e4, True),        # rattlespace weight
    ("rho3", "design", "rho3", 1e-10, 1e-6, True),      # force weight
    ("flow_feedforward_gain", "force_loop", "flow_feedforward_gain", 0.5, 1.1, False),
    ("kp_per_n", "force_loop", "kp_per_n", 3e-5, 3e-4, True),
    ("window_s", "fuzzy", "window_s", 2e-3, 0.2, True),  # only for the relative statistic
)
#: the optuna journal in the output directory
JOURNAL = "tune.journal"
STUDY_NAME = "rig-tune"
#: statistics skip this much of a run at least this long (the start-up transient) [s]
SETTLE_S = 0.5
MIN_SETTLED_RUN_S = 2.0
#: objective of a trial whose runs give no finite ratio (far from any real trial)
NO_VALUE = 1e3
METRICS = ("absorbed_power", "rattlespace_rms_m", "tire_load_rms_ratio", "n_faults",
           "bump_stop_slam", "nonfinite")


class TuneError(ValueError):
    """A search that cannot run as asked (a journal of another search, bad bound)."""


@dataclass(frozen=True)
class TunePlan:
    """What one search runs; equal plans share a journal."""

    trials: int = 40
    plants: int = 4
    spread: float = 0.05
    roads: tuple[str, ...] = ("rough-course",)
    speed_mps: float = 11.176
    duration_s: float = 10.0
    controller: str = "fuzzy"
    seed: int = 1
    #: ratio to passive, or None = the baseline's (the configuration's weight set 1)
    rattlespace_bound: float | None = 1.0
    tire_load_bound: float | None = 1.0
    #: trials evaluated together in one batch (keeps a cluster busy)
    batch: int = 1

    def key(self) -> dict[str, Any]:
        """The fields that must match to resume a journal (not the trial count)."""
        d = asdict(self)
        d.pop("trials")
        d.pop("batch")
        d["roads"] = list(self.roads)
        return d


@dataclass(frozen=True)
class TuneRun:
    """One run as it crosses to a worker."""

    trial: str             # key of the configuration in the batch's shared dict
    plant: int
    road: int
    params: PlantParams
    seed: int
    controller: str


@dataclass
class TuneResult:
    best: dict[str, Any] | None
    baseline: dict[str, Any]
    trials: list[dict[str, Any]]
    bounds: dict[str, float]
    files: list[Path] = field(default_factory=list)
    wall_s: float = 0.0
    failures: list[str] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {"best": self.best, "baseline": self.baseline, "bounds": self.bounds,
                "wall_s": self.wall_s, "files": [str(f) for f in self.files],
                "failures": self.failures, "trials": self.trials}


def _settle(duration_s: float) -> float:
    return SETTLE_S if duration_s >= MIN_SETTLED_RUN_S else 0.0


def tune_task(shared: tuple[dict[str, str], tuple[Road, ...], float], run: TuneRun
              ) -> dict[str, float]:
    """A worker's run: ``shared`` = ({trial key: configuration TOML}, roads, settle)."""
    configs, roads, settle_s = shared
    cfg = config_from_text(configs[run.trial])
    res = simulate(cfg, roads[run.road], run.controller, 1, params=run.params, seed=run.seed,
                   settle_s=settle_s)
    return {k: float(res.metrics[k]) for k in METRICS}


def active_space(cfg: RigConfig, controller: str) -> list[tuple[str, str, str, float, float,
                                                                bool]]:
    """The searched keys for this configuration (the fuzzy window only where it acts)."""
    return [s for s in SEARCH_SPACE
            if s[0] != "window_s" or (controller == "fuzzy"
                                      and cfg.fuzzy.statistic == "relative")]


def base_values(cfg: RigConfig) -> dict[str, float]:
    """The configuration's own values of the searched keys (weight set 1)."""
    w = cfg.design.weight_sets[0]
    return {"rho1": w[0], "rho2": w[1], "rho3": w[2],
            "flow_feedforward_gain": cfg.force_loop.flow_feedforward_gain,
            "kp_per_n": cfg.force_loop.kp_per_n, "window_s": cfg.fuzzy.window_s}


def trial_config(cfg: RigConfig, values: dict[str, float], keep_sets: bool = False
                 ) -> RigConfig:
    """``cfg`` with the trial's values: weights [rho1, rho2, rho3, rho4 of set 1] as weight
    set 1 (``keep_sets``: the earlier sets follow, for the written configuration)."""
    w1 = cfg.design.weight_sets[0]
    w = [float(values.get("rho1", w1[0])), float(values.get("rho2", w1[1])),
         float(values.get("rho3", w1[2])), float(w1[3])]
    sets = [w, *[list(s) for s in cfg.design.weight_sets]][:15] if keep_sets else [w]
    sections: dict[str, dict[str, Any]] = {"design": {"weight_sets": sets, "weight_set": 1}}
    for name, section, key, *_ in SEARCH_SPACE:
        if section != "design" and name in values:
            sections.setdefault(section, {})[key] = float(values[name])
    return cfg.replace(**sections)


def _ratios(runs: Sequence[dict[str, float]], passive: Sequence[dict[str, float]]
            ) -> dict[str, Any]:
    def mean_ratio(key: str) -> float:
        r = [a[key] / p[key] for a, p in zip(runs, passive, strict=True)
             if p[key] > 0 and math.isfinite(a[key])]
        return float(np.mean(r)) if r else math.nan
    return {"absorbed_power_ratio": mean_ratio("absorbed_power"),
            "rattlespace_rms_ratio": mean_ratio("rattlespace_rms_m"),
            "tire_load_rms_ratio": mean_ratio("tire_load_rms_ratio"),
            "faults": int(sum(r["n_faults"] > 0 or r["nonfinite"] > 0 for r in runs)),
            "slams": int(sum(r["bump_stop_slam"] > 0 for r in runs))}


#: the constraint names (``Trial.set_constraint``; feasible when every value is <= 0)
CONSTRAINTS = ("rattlespace", "tire_load", "faults", "slams")


def _pareto(points: np.ndarray) -> np.ndarray:
    """Mask of the points no other point is at least as good as in every column and
    better in one (all minimised)."""
    n = points.shape[0]
    keep = np.ones(n, dtype=bool)
    for i in range(n):
        dom = np.all(points <= points[i], axis=1) & np.any(points < points[i], axis=1)
        keep[i] = not dom.any()
    return keep


def plot_pareto(trials: list[dict[str, Any]], baseline: dict[str, Any],
                best: dict[str, Any] | None, path: Path, title: str) -> Path:
    """Absorbed power vs rattlespace (colour: tire load) and vs tire load (colour:
    rattlespace), ratios to passive; the feasible Pareto front outlined, infeasible
    trials hollow, the baseline a star."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = ("absorbed_power_ratio", "rattlespace_rms_ratio", "tire_load_rms_ratio")
    names = ("absorbed power", "rattlespace RMS", "dynamic tire load RMS")
    ok = [t for t in trials if all(math.isfinite(t.get(k, math.nan)) for k in keys)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), dpi=110)
    if ok:
        pts = np.array([[t[k] for k in keys] for t in ok])
        feas = np.array([t["feasible"] for t in ok], dtype=bool)
        front = np.zeros(len(ok), dtype=bool)
        if feas.any():
            front[np.flatnonzero(feas)[_pareto(pts[feas])]] = True
        for ax, (yi, ci) in zip(axes, ((1, 2), (2, 1)), strict=True):
            vmin, vmax = float(pts[:, ci].min()), float(pts[:, ci].max())
            sc = ax.scatter(pts[feas, 0], pts[feas, yi], c=pts[feas, ci], cmap="viridis",
                            vmin=vmin, vmax=vmax, s=28, zorder=3, label="feasible")
            ax.scatter(pts[~feas, 0], pts[~feas, yi], facecolors="none", edgecolors="0.6",
                       s=28, zorder=2, label="infeasible")
            ax.scatter(pts[front, 0], pts[front, yi], facecolors="none", edgecolors="k",
                       s=90, lw=1.2, zorder=4, label="Pareto front (feasible)")
            ax.plot([baseline[keys[0]]], [baseline[keys[yi]]], "r*", ms=14, zorder=5,
                    label="baseline (weight set 1)")
            if best is not None:
                ax.plot([best[keys[0]]], [best[keys[yi]]], "kx", ms=12, mew=2, zorder=6,
                        label="best")
            fig.colorbar(sc, ax=ax, label=f"{names[ci]} / passive")
            ax.set_xlabel("absorbed power / passive")
            ax.set_ylabel(f"{names[yi]} / passive")
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _plan_hash(cfg: RigConfig, plan: TunePlan) -> str:
    blob = json.dumps({"config": config_hash(cfg), "plan": plan.key()}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def _open_study(out: Path, cfg: RigConfig, plan: TunePlan) -> Any:
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = JournalStorage(JournalFileBackend(str(out / JOURNAL)))
    # constraints come from Trial.set_constraint (optuna 5 replaced constraints_func)
    sampler = optuna.samplers.TPESampler(seed=plan.seed,
                                         n_startup_trials=min(10, max(2, plan.trials // 4)),
                                         multivariate=True, constant_liar=True)
    study = optuna.create_study(study_name=STUDY_NAME, storage=storage, sampler=sampler,
                                direction="minimize", load_if_exists=True)
    key = _plan_hash(cfg, plan)
    old = study.user_attrs.get("plan_hash")
    if old is None:
        study.set_user_attr("plan_hash", key)
        study.set_user_attr("plan", plan.key())
        study.set_user_attr("config_hash", config_hash(cfg))
    elif old != key:
        raise TuneError(f"{out / JOURNAL} holds a search of another configuration or plan "
                        f"({study.user_attrs.get('plan')}); resume it with the same "
                        "arguments or use another --out")
    # trials left running by a search that was stopped: failed, so they are not waited for
    for t in study.get_trials(deepcopy=False,
                              states=(optuna.trial.TrialState.RUNNING,)):
        study.tell(t.number, state=optuna.trial.TrialState.FAIL)
    return study


def _runs(plan: TunePlan, params: list[PlantParams], key: str, controller: str
          ) -> list[TuneRun]:
    return [TuneRun(key, i, j, p, plan.seed + 1000 + i, controller)
            for i, p in enumerate(params) for j in range(len(plan.roads))]


def _case(run: TuneRun, roads: Sequence[Road]) -> str:
    p, r = run.params, roads[run.road]
    return (f"{run.trial}: plant {run.plant} (M={p.sprung_mass_kg:.4g} kg, K="
            f"{p.suspension_stiffness_n_per_m:.5g} N/m, Kt x{p.tire_stiffness_scale:.4g}), "
            f"road {r.name} at {r.speed_mps:g} m/s, sensor seed {run.seed}")


def run_tune(cfg: RigConfig, plan: TunePlan, out_dir: str | Path, executor: BatchExecutor,
             *, progress: bool = True,
             on_trial: Callable[[dict[str, Any]], None] | None = None) -> TuneResult:
    """Run (or resume) the search of ``plan`` on ``executor``; write ``tuned.toml``,
    ``pareto.png`` and ``tune.json`` into ``out_dir``."""
    from optuna.trial import TrialState
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    study = _open_study(out, cfg, plan)
    space = active_space(cfg, plan.controller)
    base = base_values(cfg)
    roads = tuple(make_road(r, plan.speed_mps, plan.duration_s, cfg.sample_time_s, plan.seed)
                  for r in plan.roads)
    settle = _settle(plan.duration_s)
    params = draw_params(cfg, plan.plants, plan.spread, plan.seed)
    failures: list[str] = []

    # passive and the configuration's weight set 1 on the same plants and roads
    ref_runs = _runs(plan, params, "passive", "passive") + _runs(plan, params, "baseline",
                                                                 plan.controller)
    text = config_to_toml(cfg)
    ref = executor.run(tune_task, ({"passive": text, "baseline": text}, roads, settle),
                       ref_runs, [_case(r, roads) for r in ref_runs], desc="tune baseline",
                       progress=progress)
    if ref.failures:
        raise TuneError("the passive / baseline runs failed: "
                        + "; ".join(str(f) for f in ref.failures[:3]))
    n_ref = len(ref_runs) // 2
    vals = ref.values()
    passive, base_runs = vals[:n_ref], vals[n_ref:]
    baseline = {"weights": list(cfg.design.weight_sets[0]),
                "settings": {s[0]: base[s[0]] for s in space if s[1] != "design"},
                **_ratios(base_runs, passive)}
    bounds = {"rattlespace_rms_ratio": (baseline["rattlespace_rms_ratio"]
                                        if plan.rattlespace_bound is None
                                        else plan.rattlespace_bound),
              "tire_load_rms_ratio": (baseline["tire_load_rms_ratio"]
                                      if plan.tire_load_bound is None
                                      else plan.tire_load_bound)}

    if not study.trials and all(lo <= base[n] <= hi for n, _, _, lo, hi, _ in space):
        study.enqueue_trial({n: base[n] for n, *_ in space})

    def finished() -> int:
        return len([t for t in study.get_trials(deepcopy=False)
                    if t.state in (TrialState.COMPLETE, TrialState.FAIL)])

    bar: Any = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=plan.trials, initial=min(finished(), plan.trials), desc="tune",
                   unit="trial")
    try:
        while finished() < plan.trials:
            k = min(plan.batch, plan.trials - finished())
            asked = [study.ask() for _ in range(k)]
            configs: dict[str, str] = {}
            values: dict[str, dict[str, float]] = {}
            runs: list[TuneRun] = []
            bad: set[int] = set()
            for tr in asked:
                v = {n: tr.suggest_float(n, lo, hi, log=log) for n, _, _, lo, hi, log in space}
                values[f"trial {tr.number}"] = v
                try:
                    configs[f"trial {tr.number}"] = config_to_toml(trial_config(cfg, v))
                except ValueError as exc:            # a configuration the schema refuses
                    failures.append(f"trial {tr.number}: {exc}")
                    bad.add(tr.number)
                    continue
                runs += _runs(plan, params, f"trial {tr.number}", plan.controller)
            res = executor.run(tune_task, (configs, roads, settle), runs,
                               [_case(r, roads) for r in runs], desc="tune trials")
            failures += [str(f) for f in res.failures]
            failed_keys = {runs[f.index].trial for f in res.failures}
            for tr in asked:
                key = f"trial {tr.number}"
                v = values[key]
                tr.set_user_attr("weights", [v["rho1"], v["rho2"], v["rho3"],
                                             float(cfg.design.weight_sets[0][3])])
                if tr.number in bad or key in failed_keys:
                    tr.set_user_attr("constraints", [1.0] * len(CONSTRAINTS))
                    study.tell(tr, state=TrialState.FAIL)
                else:
                    mine = [m for r, m in zip(runs, res.results, strict=True)
                            if r.trial == key and m is not None]
                    rat = _ratios(mine, passive)
                    for name, value in rat.items():
                        tr.set_user_attr(name, value)
                    cons = [rat["rattlespace_rms_ratio"] - bounds["rattlespace_rms_ratio"],
                            rat["tire_load_rms_ratio"] - bounds["tire_load_rms_ratio"],
                            float(rat["faults"]), float(rat["slams"])]
                    cons = [c if math.isfinite(c) else 1.0 for c in cons]
                    tr.set_user_attr("constraints", cons)
                    for name, c in zip(CONSTRAINTS, cons, strict=True):
                        tr.set_constraint(name, c)
                    obj = rat["absorbed_power_ratio"]
                    study.tell(tr, obj if math.isfinite(obj) else NO_VALUE)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()

    trials = _trial_rows(study, space, base)
    feasible = [t for t in trials if t["feasible"]]
    best = min(feasible, key=lambda t: t["absorbed_power_ratio"]) if feasible else None
    files: list[Path] = []
    if best is not None:
        tuned = trial_config(cfg, best["values"], keep_sets=True)
        path = out / "tuned.toml"
        path.write_text(_tuned_header(plan, best, baseline) + config_to_toml(tuned),
                        encoding="utf-8")
        files.append(path)
    title = (f"rig tune: {plan.controller}, {plan.plants} plants x {len(plan.roads)} roads "
             f"({', '.join(plan.roads)}), spread {plan.spread:g}, {plan.duration_s:g} s; "
             f"{len(trials)} trials")
    files.append(plot_pareto(trials, baseline, best, out / "pareto.png", title))
    files.append(out / "tune.json")
    result = TuneResult(best, baseline, trials, bounds, files,
                        time.perf_counter() - t0, failures)
    from rig import strict_json
    (out / "tune.json").write_text(strict_json.dumps(result.as_json(), indent=1) + "\n",
                                   encoding="utf-8")
    return result


def _trial_rows(study: Any, space: Sequence[tuple[str, str, str, float, float, bool]],
                base: dict[str, float]) -> list[dict[str, Any]]:
    rows = []
    for t in study.get_trials(deepcopy=False):
        if t.state.name not in ("COMPLETE", "FAIL"):
            continue
        values = {n: float(t.params.get(n, base[n])) for n, *_ in space}
        cons = t.user_attrs.get("constraints", [1.0])
        row = {"number": t.number, "state": t.state.name,
               "weights": t.user_attrs.get("weights"),
               "settings": {n: values[n] for n, section, *_ in space if section != "design"},
               "values": values,
               "feasible": t.state.name == "COMPLETE" and all(c <= 0 for c in cons),
               "constraints": list(cons)}
        for key in ("absorbed_power_ratio", "rattlespace_rms_ratio", "tire_load_rms_ratio",
                    "faults", "slams"):
            row[key] = t.user_attrs.get(key, math.nan)
        rows.append(row)
    return rows


def _tuned_header(plan: TunePlan, best: dict[str, Any], baseline: dict[str, Any]) -> str:
    return (f"# written by rig tune (trial {best['number']}): weight set 1 is the tuned set "
            f"(the earlier sets follow)\n# {plan.plants} plants x {', '.join(plan.roads)} at "
            f"{plan.speed_mps:g} m/s, spread {plan.spread:g}, {plan.duration_s:g} s, seed "
            f"{plan.seed}, controller {plan.controller}\n# absorbed power / passive "
            f"{best['absorbed_power_ratio']:.4f} (weight set 1 before: "
            f"{baseline['absorbed_power_ratio']:.4f}), rattlespace RMS / passive "
            f"{best['rattlespace_rms_ratio']:.4f} ({baseline['rattlespace_rms_ratio']:.4f}), "
            f"tire load RMS / passive {best['tire_load_rms_ratio']:.4f} "
            f"({baseline['tire_load_rms_ratio']:.4f})\n\n")
