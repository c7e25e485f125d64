"""Scale-out of the batch seam (hil/batch.py): Dask on 127.0.0.1 against the local pool.

``run(quick=False) -> list[dict]`` measures, on this machine:

* ``equal``: a Monte Carlo (``runs`` x ``duration`` s, fuzzy, 5 % spread) on a Dask
  ``LocalCluster`` (2 workers, tcp://127.0.0.1) and on the local process pool: the rows
  bit-identical (every metric but the wall-clock real-time factor, every trace);
* ``throughput``: the same Monte Carlo on 1 and 2 Dask workers and on the 2-process local
  pool after a warm-up batch (numba and the design already loaded on every worker):
  runs per second (the best of 3 repeats, interleaved between the executors so each
  sees the same neighbours: the machine may be shared) and the 2 / 1 worker ratio;
* ``overhead``: a batch of near-empty tasks (``operator.add``) through each executor:
  wall time per task, the cost the seam adds to every run.

The projection for N machines of c cores (docs/scale-out.md): runs per second ~
min(N c / t_run, 1 / t_task) -- t_run (one run on one worker) from the throughput rows,
t_task (the wall time per task of a batch of empty tasks: what one scheduler and one
client can hand out) from the overhead rows.
``python -m bench scale_out`` prints the table.
"""

from __future__ import annotations

import logging
import math
import operator
import time
from typing import Any

import numpy as np

from controller.config import default_config
from hil.batch import BatchExecutor, DaskExecutor, LocalExecutor, parse_cluster_address
from hil.sim.montecarlo import MonteCarloResult, run_montecarlo
from hil.sim.roads import make_road

NAME = "scale_out"
TITLE = "Batch seam: Dask on 127.0.0.1 vs the local process pool"


def _same(a: MonteCarloResult, b: MonteCarloResult) -> bool:
    for ra, rb in zip(a.runs, b.runs, strict=True):
        for k in ra:
            x, y = ra[k], rb[k]
            if k == "realtime_factor" or x == y:
                continue
            if isinstance(x, float) and isinstance(y, float) and math.isnan(x) \
                    and math.isnan(y):
                continue
            return False
    return all(np.array_equal(x, y) for x, y in zip(a.traces, b.traces, strict=True))


def _mc(ex: BatchExecutor, runs: int, duration_s: float, seed: int) -> tuple[float,
                                                                             MonteCarloResult]:
    cfg = default_config()
    road = make_road("rough-course", 11.176, duration_s, cfg.sample_time_s, 1)
    t0 = time.perf_counter()
    res = run_montecarlo(cfg, road, runs, controller="fuzzy", spread=0.05, seed=seed,
                         progress=False, executor=ex)
    return time.perf_counter() - t0, res


def _dask(workers: int) -> DaskExecutor:
    logging.getLogger("distributed").setLevel(logging.ERROR)
    return DaskExecutor(parse_cluster_address(f"local:{workers}"))


def _overhead(ex: BatchExecutor, n: int) -> float:
    ex.run(operator.add, 0, list(range(2 * ex.workers)), ["warm-up"] * 2 * ex.workers)
    t0 = time.perf_counter()
    res = ex.run(operator.add, 1, list(range(n)), [f"task {i}" for i in range(n)])
    dt = time.perf_counter() - t0
    assert res.values() == [i + 1 for i in range(n)]
    return dt / n


def run(quick: bool = False) -> list[dict[str, Any]]:
    runs, duration, n_empty, repeats = (8, 2.0, 100, 1) if quick else (40, 10.0, 1000, 3)
    rows: list[dict[str, Any]] = []
    results: dict[str, MonteCarloResult] = {}
    walls: dict[str, float] = {}
    exs: dict[str, BatchExecutor] = {"local pool, 2 processes": LocalExecutor(2),
                                     "dask, 1 worker": _dask(1), "dask, 2 workers": _dask(2)}
    try:
        for ex in exs.values():
            _mc(ex, ex.workers * 2, duration, seed=99)           # warm-up: numba, design
        tries: dict[str, list[tuple[float, MonteCarloResult]]] = {k: [] for k in exs}
        for _ in range(repeats):         # interleaved: each executor sees the same load
            for label, ex in exs.items():
                tries[label].append(_mc(ex, runs, duration, seed=1))
        for label, ex in exs.items():
            walls[label] = min(w for w, _ in tries[label])      # least disturbed
            results[label] = tries[label][0][1]
            assert all(_same(results[label], r) for _, r in tries[label][1:])
            per_task = min(_overhead(ex, n_empty) for _ in range(repeats))
            rows.append({"executor": label, "runs": runs, "run_s": duration,
                         "wall_s": walls[label], "runs_per_s": runs / walls[label],
                         "empty_task_ms": 1e3 * per_task})
    finally:
        for ex in exs.values():
            ex.close()
    with LocalExecutor(1) as ex:                     # CPU time of one run, this process
        _mc(ex, 2, duration, seed=99)
        c0 = time.process_time()
        _mc(ex, runs // 4, duration, seed=1)
        cpu = (time.process_time() - c0) / (runs // 4)
    rows.append({"executor": "in-process, CPU seconds per run", "runs": runs // 4,
                 "run_s": duration, "wall_s": math.nan, "runs_per_s": 1.0 / cpu,
                 "empty_task_ms": math.nan, "cpu_s_per_run": cpu})
    one, two = walls["dask, 1 worker"], walls["dask, 2 workers"]
    rows.append({"executor": "dask 2 / 1 worker speed-up", "runs": runs, "run_s": duration,
                 "wall_s": math.nan, "runs_per_s": one / two, "empty_task_ms": math.nan})
    equal = all(_same(results["local pool, 2 processes"], results[k])
                for k in ("dask, 1 worker", "dask, 2 workers"))
    rows.append({"executor": "dask == local pool (bit-identical)", "runs": runs,
                 "run_s": duration, "wall_s": math.nan, "runs_per_s": float(equal),
                 "empty_task_ms": math.nan})
    return rows


def notes(rows: list[dict[str, Any]]) -> list[str]:
    by = {r["executor"]: r for r in rows}
    one = by["dask, 1 worker"]
    t_run = by["in-process, CPU seconds per run"]["cpu_s_per_run"]
    t_task = by["dask, 2 workers"]["empty_task_ms"] * 1e-3
    out = [f"one {one['run_s']:g} s run takes {t_run:.3f} s of CPU; a batch of empty "
           f"tasks goes through Dask at {1e3 * t_task:.2f} ms per task (the ceiling: "
           f"{1 / t_task:.0f} tasks/s through one scheduler and client)"]
    for n_cores in (8, 64, 512):
        rate = min(n_cores / t_run, 1.0 / t_task)
        out.append(f"projection, {n_cores} worker cores: ~{rate:.0f} runs/s of "
                   f"{one['run_s']:g} s (min(cores / t_run, 1 / t_task))")
    return out


if __name__ == "__main__":
    import sys
    rs = run(quick="--quick" in sys.argv[1:])
    for r in rs:
        print(r)
    for line in notes(rs):
        print(line)
