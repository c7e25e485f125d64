"""``run_study``: skyhook search, the matrix, ratios, linear trade-off, tables, figures."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import RigConfig, config_hash
from hil.batch import BatchExecutor, LocalExecutor
from hil.sim.closed_loop import cached_design
from hil.sim.skyhook import DEFAULT_GAINS, SkyhookGains, select_gains
from hil.study.matrix import (
    DEFAULT_GROUPS,
    add_ratios,
    plan,
    run_cases,
    selected,
    study_cases,
    tune_cases,
)
from hil.study.report import claim_values, claims, tables_markdown, write_csv, write_figures
from hil.study.tradeoff import TradeoffGrid, tradeoff_grid
from rig import strict_json

__all__ = ["StudyResult", "run_study"]

#: (rho1, rho2) axes of the linear trade-off surface (rho3 = 1e-8, rho4 = 1)
SURFACE_RHO1 = (1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3, 1e4)
SURFACE_RHO2 = (*(float(x) for x in np.round(np.logspace(-3, 4, 22), 10)),
                0.01, 0.1, 1.0, 10.0, 100.0, 300.0, 1000.0)


@dataclass
class StudyResult:
    rows: list[dict[str, Any]]
    skyhook: SkyhookGains
    claims: list[tuple[str, str, bool]]
    files: list[Path]
    wall_s: float


def run_study(cfg: RigConfig, out_dir: str | Path, *, quick: bool = False,
              jobs: int | None = None, progress: bool = True,
              executor: BatchExecutor | None = None,
              groups: Sequence[str] = DEFAULT_GROUPS) -> StudyResult:
    """Run the study's ``groups`` (``hil.study.matrix.GROUPS``) and write ``results.md``,
    ``results.csv``, the PNG figures of what ran and, when the ``main`` group ran,
    ``claims.json`` into ``out_dir`` (created).  Without the ``tune`` group the skyhook
    runs use :data:`hil.sim.skyhook.DEFAULT_GAINS` (the search's result); without ``rho``
    there is no linear trade-off grid.  The runs go to ``executor`` (default: a local
    pool of ``jobs`` processes); :class:`hil.batch.BatchError` names failed runs."""
    if executor is None:
        with LocalExecutor(jobs) as ex:
            return run_study(cfg, out_dir, quick=quick, jobs=jobs, progress=progress,
                             executor=ex, groups=groups)
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = plan(quick)
    tcases = selected(tune_cases(p), groups)
    trows: list[dict[str, Any]] = []
    sky = DEFAULT_GAINS
    if tcases:
        trows = run_cases(tcases, cfg, jobs, progress, "skyhook search", executor)
        add_ratios(trows, tcases)
        sky = select_gains([r for r, c in zip(trows, tcases, strict=True)
                            if c.controller == "skyhook"])
    cases = study_cases(p, cfg, sky, groups)
    rows = run_cases(cases, cfg, jobs, progress, "study matrix", executor) if cases else []
    add_ratios(rows, cases)
    rows = trows + rows
    grid: TradeoffGrid | None = None
    if "rho" in groups:
        rho2 = sorted(set(SURFACE_RHO2[::4] if quick else SURFACE_RHO2) | set(p.rho2_checks))
        grid = tradeoff_grid(cfg, SURFACE_RHO1, rho2,
                             rig_rho1=(1.0,) if quick else (1.0, 10.0))
    firing = None
    if "main" in groups:
        design = cached_design(cfg)
        firing = (np.asarray(design.fuzzy_q_grid), np.asarray(design.fuzzy_weight_curve),
                  [str(n) for n in design.model_names])
    files = write_figures(rows, out, grid, firing, cfg.design.weight_sets)
    wall = time.perf_counter() - t0
    n_jobs = max(1, executor.workers)
    describe = f"groups {', '.join(g for g in groups)}; {p.describe()}"
    md = tables_markdown(rows, grid, sky, describe, wall, n_jobs, cfg)
    (out / "results.md").write_text(md + "\n", encoding="utf-8")
    write_csv(rows, out / "results.csv")
    files = [out / "results.md", out / "results.csv", *files]
    cl: list[tuple[str, str, bool]] = []
    if "main" in groups:
        cl = claims(rows)
        (out / "claims.json").write_text(strict_json.dumps(
            {"quick": quick, "config_hash": config_hash(cfg), "groups": list(groups),
             "thesis_case": {"duration_s": p.thesis_duration_s,
                             "seeds": list(p.thesis_seeds), "settle_s": p.settle_s},
             "skyhook": asdict(sky), "values": claim_values(rows),
             "claims": [{"claim": c, "measured": m, "holds": ok} for c, m, ok in cl]},
            indent=1) + "\n", encoding="utf-8")
        files.insert(2, out / "claims.json")
    return StudyResult(rows, sky, cl, files, wall)
