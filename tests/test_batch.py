"""The batch seam (hil/batch.py): local process pool and a real Dask cluster on 127.0.0.1
give the same results, failures keep their case, a lost worker's task is rerun."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest

from controller.config import default_config
from hil import batch
from hil.batch import (
    BatchError,
    ClusterAddress,
    ClusterAddressError,
    ClusterError,
    DaskExecutor,
    LocalExecutor,
    parse_cluster_address,
)
from hil.sim import montecarlo
from hil.sim.montecarlo import run_montecarlo
from hil.sim.roads import make_road
from rig.cli import main
from tests.support import batch_tasks

# the workers of the test cluster need not find tests/ on their path
cloudpickle.register_pickle_by_value(batch_tasks)

CFG = default_config()


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A real scheduler and two worker processes on 127.0.0.1 (no dashboard), closed
    after the module; yields its tcp:// address."""
    import logging

    from distributed import LocalCluster
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None,
                           scheduler_kwargs=batch.LOCAL_HTTP,
                           silence_logs=logging.CRITICAL)
    try:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def dask_ex(scheduler: str) -> Iterator[DaskExecutor]:
    with DaskExecutor(parse_cluster_address(scheduler)) as ex:
        yield ex


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


def _assert_runs_equal(a: montecarlo.MonteCarloResult,
                       b: montecarlo.MonteCarloResult) -> None:
    assert len(a.runs) == len(b.runs)
    for ra, rb in zip(a.runs, b.runs, strict=True):
        assert ra.keys() == rb.keys()
        diff = {k for k in ra if k != "realtime_factor" and not _same(ra[k], rb[k])}
        assert not diff, diff            # bit-identical (only the wall-clock rate differs)
    assert all(np.array_equal(x, y) for x, y in zip(a.traces, b.traces, strict=True))
    assert a.unstable_runs == b.unstable_runs and a.faulted_runs == b.faulted_runs


def test_montecarlo_on_dask_equals_the_local_run(dask_ex: DaskExecutor) -> None:
    road = make_road("rough-course", 11.176, 1.0, CFG.sample_time_s, 1)
    kw: dict[str, Any] = {"controller": "fuzzy", "spread": 0.1, "seed": 4,
                          "progress": False}
    local = run_montecarlo(CFG, road, 4, workers=2, **kw)
    serial = run_montecarlo(CFG, road, 4, workers=1, **kw)
    on_dask = run_montecarlo(CFG, road, 4, executor=dask_ex, **kw)
    assert dask_ex.workers == 2
    assert not local.failed_runs and not on_dask.failed_runs
    _assert_runs_equal(local, on_dask)
    _assert_runs_equal(serial, on_dask)
    # different plants really were run (the comparison is not between copies of one run)
    assert len({r["absorbed_power"] for r in on_dask.runs}) == 4


@pytest.mark.parametrize("kind", ["dask", "local-pool", "in-process"])
def test_a_task_that_raises_is_reported_with_its_case(kind: str,
                                                     request: pytest.FixtureRequest) -> None:
    ex: Any = (request.getfixturevalue("dask_ex") if kind == "dask"
               else LocalExecutor(2 if kind == "local-pool" else 1))
    items = list(range(6))
    cases = [f"plant {i}, road iso-B, seed {100 + i}" for i in items]
    res = ex.run(batch_tasks.square_or_raise, 1, items, cases, desc="squares",
                 order=[5, 4, 3, 2, 1, 0])
    if kind != "dask":
        ex.close()
    assert res.results == [1, 4, 9, None, 25, 36]          # by task index, not by order
    assert [(f.index, f.case) for f in res.failures] == [(3, "plant 3, road iso-B, seed 103")]
    assert res.failures[0].error == "ValueError: task input 3 is refused"
    with pytest.raises(BatchError, match=r"1 of 6 tasks failed: task 3 \(plant 3, road "
                                         r"iso-B, seed 103\): ValueError"):
        res.values()


def test_a_lost_worker_has_its_task_rerun(dask_ex: DaskExecutor, tmp_path: Path) -> None:
    """Task 1 kills its worker process (os._exit) the first time; the scheduler reruns it
    on a live worker (the nanny restarts the dead one) and the batch completes."""
    res = dask_ex.run(batch_tasks.die_once, str(tmp_path), [0, 1, 2], ["a", "b", "c"])
    assert (tmp_path / "died-1").exists()                  # a worker really died
    assert res.failures == []
    assert res.results == [0, 10, 20]


def test_montecarlo_failure_names_plant_road_and_seed(monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    real = montecarlo.simulate

    def flaky(cfg: Any, road: Any, *a: Any, seed: int | None = None, **kw: Any) -> Any:
        if seed == 1001 + 1000 + 1:                     # run 1 of --seed 1001
            raise FloatingPointError("plant state blew up")
        return real(cfg, road, *a, seed=seed, **kw)

    monkeypatch.setattr(montecarlo, "simulate", flaky)
    road = make_road("iso-B", 20.0, 0.2, CFG.sample_time_s, 1)
    res = run_montecarlo(CFG, road, 3, controller="passive", seed=1001, workers=1,
                         progress=False)
    assert [r["run"] for r in res.runs] == [0, 2]
    [f] = res.failed_runs
    assert f["run"] == 1 and f["error"] == "FloatingPointError: plant state blew up"
    assert f["case"].startswith("run 1: M=") and "road iso-B at 20 m/s" in f["case"]
    assert f["case"].endswith("sensor seed 2002")
    assert main(["montecarlo", "--runs", "3", "--seed", "1001", "--road", "iso-B",
                 "--speed", "20", "--duration", "0.2", "--controller", "passive",
                 "--jobs", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "run 1: M=" in err[0] and "plant state blew up" in err[0]


@pytest.mark.parametrize(("text", "expected"), [
    ("tcp://127.0.0.1:8786", ClusterAddress("tcp", "127.0.0.1", 8786)),
    ("tcp://scheduler.lab.example:1", ClusterAddress("tcp", "scheduler.lab.example", 1)),
    ("tcp://[::1]:65535", ClusterAddress("tcp", "[::1]", 65535)),
    ("local:3", ClusterAddress("local", workers=3)),
])
def test_cluster_addresses(text: str, expected: ClusterAddress) -> None:
    assert parse_cluster_address(text) == expected
    assert str(expected) == text


@pytest.mark.parametrize("text", ["127.0.0.1:8786", "tcp://127.0.0.1", "tcp://:8786",
                                  "tcp://127.0.0.1:0", "tcp://127.0.0.1:65536",
                                  "tcp://host name:1", "tls://127.0.0.1:8786", "local:0",
                                  "local:x", f"local:{batch.MAX_LOCAL_WORKERS + 1}", ""])
def test_bad_cluster_addresses_are_one_line_errors(text: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ClusterAddressError, match="allowed tcp://HOST:PORT or local:N"):
        parse_cluster_address(text)
    for cmd in (["montecarlo"], ["study"]):
        assert main([*cmd, "--cluster", text]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--cluster" in err and "Traceback" not in err


def test_unreachable_scheduler_is_a_one_line_error() -> None:
    with pytest.raises(ClusterError, match=r"cannot reach the Dask scheduler at "
                                           r"tcp://127.0.0.1:9"):
        DaskExecutor(parse_cluster_address("tcp://127.0.0.1:9"), connect_timeout_s=1.0)


def test_workers_and_cluster_together_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["montecarlo", "--cluster", "local:1", "--jobs", "2"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_a_scheduler_without_workers_is_refused() -> None:
    import logging

    from distributed import LocalCluster
    with LocalCluster(n_workers=0, processes=True, host="127.0.0.1",
                      dashboard_address=None, scheduler_kwargs=batch.LOCAL_HTTP,
                      silence_logs=logging.CRITICAL) as cluster, \
            pytest.raises(ClusterError, match="has no workers"):
        DaskExecutor(parse_cluster_address(cluster.scheduler_address), connect_timeout_s=1.0)
