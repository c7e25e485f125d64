"""Monte Carlo robustness runs (thesis Ch. IV): the plant's M, m, K, Kt, C, Ct drawn
normal around nominal, the controller kept at its nominal design.

Ride height: the bump stops are part of the rig's geometry (centred on the nominal static
rattlespace M_nom g / K_nom), and a rig technician sets the ride height of whatever
body and spring are fitted by the spring preload.  So a drawn plant does not sit at its
own M g / K (a 15 % plant would sit up to ~76 mm off centre with 80 mm of travel): its
static position is the stops' centre plus a setting error drawn as its own parameter,
N(0, ``ride_height_std_m``) (default :data:`RIDE_HEIGHT_STD_M` = 2 mm: the technician
sets it to within a few millimetres; ``PlantParams.ride_height_offset_m``).

Runs execute through the batch seam (:mod:`hil.batch`: a local process pool, one
process per core by default, or a Dask cluster) with a tqdm progress bar; what crosses to
a worker is the configuration as TOML text and the road profile (once per batch) and per
run the plant parameters and seed.  A run that raises is listed with its plant, road
and seed in ``failed_runs``.  Each run is a :func:`hil.sim.closed_loop.simulate` call;
the summary gives mean / std / min / max of every metric and lists the unstable runs
(non-finite state, bump-stop slamming) and the runs with a latched fault.  ``plot_runs``
draws the rattlespace traces of all runs (like the thesis's Fig. 4.1) with matplotlib's
Agg backend.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig, config_to_toml
from hil.batch import BatchExecutor, LocalExecutor
from hil.sim.closed_loop import (
    CONTROLLERS,
    config_from_text,
    simulate,
)
from hil.sim.plant import PlantParams
from hil.sim.roads import Road

__all__ = ["MAX_RIDE_HEIGHT_STD_M", "RIDE_HEIGHT_STD_M", "MonteCarloResult", "RunSpec",
           "draw_params", "plot_runs", "run_case_label", "run_montecarlo", "run_task",
           "summarise"]


#: a drawn factor is kept at least this fraction of nominal (a 5 % spread never gets here)
MIN_FACTOR = 0.2
TRACE_DECIMATION = 10
#: standard deviation of the ride-height setting error [m] (static rattlespace minus the
#: bump stops' centre after the technician adjusted the spring preload)
RIDE_HEIGHT_STD_M = 0.002
#: largest ride-height setting error accepted [m] (beyond it the stops' 80 mm of travel
#: are no longer a plausible setting)
MAX_RIDE_HEIGHT_STD_M = 0.05


@dataclass
class MonteCarloResult:
    runs: list[dict[str, Any]]                 # params + metrics per run, in run order
    summary: dict[str, dict[str, float]]       # metric -> mean, std, min, max
    unstable_runs: list[int]
    faulted_runs: list[int]
    traces: list[FloatArray] = field(default_factory=list)   # decimated rattlespace [m]
    trace_dt_s: float = 0.0
    png: str | None = None
    #: runs that raised: {"run", "case", "error"} (their metrics are not in ``runs``)
    failed_runs: list[dict[str, Any]] = field(default_factory=list)


#: largest relative standard deviation of a parameter (a 3-sigma draw at 0.5 is already
#: clamped at MIN_FACTOR)
MAX_SPREAD = 0.5


def draw_params(cfg: RigConfig, runs: int, spread: float | dict[str, float] = 0.05,
                seed: int = 0, ride_height_std_m: float | None = RIDE_HEIGHT_STD_M
                ) -> list[PlantParams]:
    """``runs`` plant perturbations: each of M, m, K, C, Kt (scale), Ct (scale) is
    the emulated rig's (``cfg.emulator``: the configured values times its scales)
    x N(1, spread) (``spread`` may be per parameter: keys M, m, K, C, Kt, Ct),
    and the ride height (static rattlespace about the stops' centre, set by spring
    preload) is N(0, ``ride_height_std_m``) [m]; None keeps each plant at its own
    M g / K (no preload adjustment).  The ride heights come from their own random stream,
    so the same seed gives the same M, m, K, C, Kt, Ct whatever the ride-height setting,
    and the first k of n draws are the k draws."""
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    if ride_height_std_m is not None and not (math.isfinite(ride_height_std_m)
                                              and 0.0 <= ride_height_std_m
                                              <= MAX_RIDE_HEIGHT_STD_M):
        raise ValueError(f"ride_height_std_m must be in [0, {MAX_RIDE_HEIGHT_STD_M:g}] m, "
                         f"got {ride_height_std_m}")
    names = ("M", "m", "K", "C", "Kt", "Ct")
    if isinstance(spread, dict):
        unknown = set(spread) - set(names)
        if unknown:
            raise ValueError(f"unknown spread keys {sorted(unknown)}: use {names}")
        sd = np.array([spread.get(n, 0.05) for n in names])
    else:
        sd = np.full(len(names), float(spread))
    if np.any(~np.isfinite(sd)) or np.any(sd < 0) or np.any(sd > MAX_SPREAD):
        raise ValueError(f"spread must be in [0, {MAX_SPREAD}], got {spread}")
    rng = np.random.default_rng(seed)
    factors = np.maximum(1.0 + sd * rng.standard_normal((runs, len(names))), MIN_FACTOR)
    offsets: list[float | None] = [None] * runs
    if ride_height_std_m is not None:       # own stream: run i's draw does not depend on runs
        rng_rh = np.random.default_rng([seed, 1])
        offsets = [float(x) for x in ride_height_std_m * rng_rh.standard_normal(runs)]
    v, e = cfg.vehicle, cfg.emulator
    base = (v.sprung_mass_kg * e.sprung_mass_scale, v.unsprung_mass_kg * e.unsprung_mass_scale,
            v.suspension_stiffness_n_per_m * e.spring_rate_scale,
            v.suspension_damping_ns_per_m * e.damping_scale, e.tire_stiffness_scale)
    if not e.is_nominal:                # drawn about the emulated rig's ride height
        offsets = [None if off is None else e.ride_height_offset_m + off for off in offsets]
    return [PlantParams(sprung_mass_kg=base[0] * f[0], unsprung_mass_kg=base[1] * f[1],
                        suspension_stiffness_n_per_m=base[2] * f[2],
                        suspension_damping_ns_per_m=base[3] * f[3],
                        tire_stiffness_scale=base[4] * float(f[4]),
                        tire_damping_scale=float(f[5]), ride_height_offset_m=off)
            for f, off in zip(factors, offsets, strict=True)]


@dataclass(frozen=True)
class RunSpec:
    """One Monte Carlo run as it crosses to a worker: plant and sensor seed."""

    index: int
    params: PlantParams
    seed: int


def run_task(shared: tuple[str, Road, str, int, float], spec: RunSpec
             ) -> tuple[dict[str, float], FloatArray]:
    """A worker's run: ``shared`` = (configuration TOML, road, controller, weight set,
    time observed before arming); the bank is designed on the worker (memoised per
    configuration)."""
    config_toml, road, controller, weight_set, observe_s = shared
    cfg = config_from_text(config_toml)
    res = simulate(cfg, road, controller, weight_set, params=spec.params, seed=spec.seed,
                   observe_s=observe_s)
    return res.metrics, res.traces["rattlespace_m"][::TRACE_DECIMATION].copy()


def run_case_label(spec: RunSpec, road: Road) -> str:
    """What a run is, for a failure report: plant, road and seed."""
    p = spec.params
    return (f"run {spec.index}: M={p.sprung_mass_kg:.4g} kg m={p.unsprung_mass_kg:.4g} kg "
            f"K={p.suspension_stiffness_n_per_m:.5g} N/m C={p.suspension_damping_ns_per_m:.4g} "
            f"Ns/m Kt x{p.tire_stiffness_scale:.4g} Ct x{p.tire_damping_scale:.4g}, road "
            f"{road.name} at {road.speed_mps:g} m/s, sensor seed {spec.seed}")


def summarise(metrics: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """mean, std, min, max of every metric over the runs (NaN-aware)."""
    out: dict[str, dict[str, float]] = {}
    for key in metrics[0]:
        x = np.array([m[key] for m in metrics], dtype=float)
        finite = x[np.isfinite(x)]
        if finite.size == 0:
            out[key] = {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan}
            continue
        out[key] = {"mean": float(finite.mean()), "std": float(finite.std()),
                    "min": float(finite.min()), "max": float(finite.max())}
    return out


def run_montecarlo(cfg: RigConfig, road: Road, runs: int, *, controller: str = "fuzzy",
                   weight_set: int = 1, spread: float | dict[str, float] = 0.05,
                   seed: int = 0, workers: int | None = None, progress: bool = True,
                   out_dir: str | Path | None = None,
                   ride_height_std_m: float | None = RIDE_HEIGHT_STD_M,
                   executor: BatchExecutor | None = None,
                   observe_s: float = 0.0) -> MonteCarloResult:
    """Run ``runs`` perturbed plants in parallel (on ``executor``, default a local pool
    of ``workers`` processes); write ``montecarlo.png`` (and
    ``montecarlo.json``) into ``out_dir`` if given.

    The plants are drawn around the emulated rig of ``cfg.emulator`` (its scales and
    ride-height offset; the controller is designed from the configuration).  Where each
    rig's LVDT reads 0 is ``cfg.emulator.lvdt_zero``: ``"actual"`` (default) zeroes it at
    the rig's own static position (calibrated at rest, like the thesis's
    deviation-coordinate models); ``"nominal"`` keeps the configured zero, so the
    controller also sees the static offset M g / K - M_nom g / K_nom (about 9 mm for +5 %
    M) -- or, with the ride height set by preload (``ride_height_std_m``, see the module
    docstring), the setting error.  ``observe_s``: each run observed that long before
    arming (``hil.sim.closed_loop.run_closed_loop``; the road covers it, the metrics are
    the armed time's).
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}: use one of "
                         f"{', '.join(CONTROLLERS)}")
    if not 0 <= weight_set <= len(cfg.design.weight_sets):
        raise ValueError(f"weight set {weight_set} not in 0..{len(cfg.design.weight_sets)} "
                         f"(0 = travel schedule)")
    params = draw_params(cfg, runs, spread, seed, ride_height_std_m)
    specs = [RunSpec(i, p, seed + 1000 + i) for i, p in enumerate(params)]
    own = executor is None
    ex: BatchExecutor = (LocalExecutor(min(workers or os.cpu_count() or 1, runs))
                         if executor is None else executor)
    try:
        batch = ex.run(run_task, (config_to_toml(cfg), road, controller, weight_set,
                                  observe_s), specs,
                       [run_case_label(s, road) for s in specs],
                       desc=f"monte carlo {controller}", progress=progress)
    finally:
        if own:
            ex.close()
    done = [(i, r[0], r[1]) for i, r in enumerate(batch.results) if r is not None]
    metrics = [m for _, m, _ in done]
    run_rows = [{"run": i, **{k: v for k, v in asdict(params[i]).items()}, **m}
                for i, m, _ in done]
    result = MonteCarloResult(
        runs=run_rows, summary=summarise(metrics) if metrics else {},
        unstable_runs=[i for i, m, _ in done if m["unstable"]],
        faulted_runs=[i for i, m, _ in done if m["n_faults"]],
        traces=[tr for _, _, tr in done], trace_dt_s=road.dt_s * TRACE_DECIMATION,
        failed_runs=[{"run": f.index, "case": f.case, "error": f.error}
                     for f in batch.failures])
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        title = (f"Monte Carlo: {controller} (weights {weight_set}), {road.name} at "
                 f"{road.speed_mps:g} m/s, {runs} runs")
        result.png = str(plot_runs(result, out / "montecarlo.png", title))
        from rig.strict_json import dumps
        (out / "montecarlo.json").write_text(dumps(
            {"summary": result.summary, "unstable_runs": result.unstable_runs,
             "faulted_runs": result.faulted_runs, "failed_runs": result.failed_runs,
             "runs": result.runs}, indent=1))
    return result


def plot_runs(result: MonteCarloResult, path: str | Path, title: str = "") -> Path:
    """Rattlespace traces of every run on one axis (thesis Fig. 4.1 style)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    for i, tr in enumerate(result.traces):
        t = np.arange(tr.shape[0]) * result.trace_dt_s
        if i in result.unstable_runs:    # unstable runs: black dashed, on top
            ax.plot(t, 1000.0 * tr, "k--", lw=1.2, zorder=3, label=f"run {i} unstable")
        else:
            ax.plot(t, 1000.0 * tr, "-", lw=0.7, alpha=0.8)
    if result.unstable_runs:
        ax.legend(fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("rattlespace about static [mm]")
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p)
    plt.close(fig)
    return p
