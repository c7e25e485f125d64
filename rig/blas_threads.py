"""One BLAS thread per process, in every process the project starts.

The closed-loop runs are deterministic only if their linear algebra is: a threaded BLAS
(numpy's and scipy's OpenBLAS) splits a product differently with the number of threads
and the machine's load, so a Monte Carlo run on a Dask worker differed from the same run
in a local worker in the last digits, and the study's committed figures did not
regenerate.  A threaded BLAS pool is also unsafe to fork: a child forked while the
parent's pool was busy waits forever for threads that do not exist in it.  The work here
is many small matrices (4x4 to 12x12 in the design, a few 100 x 100 in the study), where
threads buy nothing; the batch layer (hil.batch) parallelises across processes instead.

:func:`one_blas_thread` sets the thread-count variables (for BLAS libraries loaded later
and for child processes) and limits the libraries already loaded (threadpoolctl).  The
entry points call it: ``rig`` (rig.cli), the local and Dask batch workers (hil.batch) and
the test session (tests/conftest.py).
"""

from __future__ import annotations

import os

__all__ = ["BLAS_THREAD_VARIABLES", "one_blas_thread"]

#: read by OpenBLAS, OpenMP runtimes, MKL and BLIS when they load
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                         "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")

_limited_pid: int | None = None


def one_blas_thread() -> None:
    """Limit this process (and the processes it starts) to one BLAS thread.  Cheap after
    the first call in a process."""
    global _limited_pid
    if _limited_pid == os.getpid():
        return
    for name in BLAS_THREAD_VARIABLES:
        os.environ[name] = "1"
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api="blas")
    _limited_pid = os.getpid()
