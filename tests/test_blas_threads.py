"""rig.blas_threads: one BLAS thread in the test session, in `rig` and in batch workers."""

from __future__ import annotations

import os
import subprocess
import sys

from threadpoolctl import threadpool_info

from hil.batch import LocalExecutor
from rig.blas_threads import BLAS_THREAD_VARIABLES


def _blas_threads(_shared: None, _item: int) -> list[int]:
    import scipy.linalg  # noqa: F401  (loads scipy's own BLAS too)
    return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]


def test_the_session_and_local_workers_run_one_blas_thread() -> None:
    assert all(os.environ[v] == "1" for v in BLAS_THREAD_VARIABLES)
    assert set(_blas_threads(None, 0)) == {1}
    with LocalExecutor(jobs=2) as ex:
        res = ex.run(_blas_threads, None, [0, 1], ["a", "b"])
    assert not res.failures and all(set(r) == {1} for r in res.values())


def test_a_fresh_interpreter_that_asked_for_two_threads_runs_one() -> None:
    """BLAS already loaded with 2 threads (the variables asked for 2): the call limits it."""
    env = {**os.environ, **{v: "2" for v in BLAS_THREAD_VARIABLES}}
    code = ("import scipy.linalg, threadpoolctl\n"
            "from rig.blas_threads import one_blas_thread\n"
            "def threads(): return sorted({d['num_threads'] for d in "
            "threadpoolctl.threadpool_info() if d['user_api'] == 'blas'})\n"
            "before = threads(); one_blas_thread(); print(before, threads())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True, timeout=120).stdout.strip()
    assert out == "[2] [1]"
