"""One seam for every batch of closed-loop runs: a local process pool or a Dask cluster.

The study (``rig study``), the Monte Carlo (``rig montecarlo``) and the weight search
(``rig tune``) hand their runs to a :class:`BatchExecutor`::

    with make_executor(cluster, jobs) as ex:            # cluster: None | ClusterAddress
        res = ex.run(fn, shared, items, cases, desc="monte carlo", progress=True)
    res.results     # fn(shared, items[i]) at index i (None where it failed)
    res.failures    # [TaskFailure(index, case, error)], the case names plant/road/seed

``fn`` is a module-level function (workers import it by name: they run the same
project version); ``shared`` is what every task of the batch needs (the configuration
as TOML text, a road profile), sent once per batch to each worker; ``items`` are the
per-task specifications (plant parameters, seeds).  No design artifact, file path or
open object crosses the wire: a worker designs the bank from the configuration itself
(memoised per process, ``hil.sim.closed_loop.cached_design``).

Every task is seeded by its item and the results are put back by task index, so a batch
gives bit-identical results on either executor and whatever order the tasks finish in.
A task that raises is reported with its case (not lost, not fatal to the others).

* :class:`LocalExecutor` (the default): ``concurrent.futures.ProcessPoolExecutor`` with
  ``jobs`` processes kept for the executor's life (so a worker's memoised designs are
  reused across batches); ``jobs == 1`` runs in this process.
* :class:`DaskExecutor` (``--cluster ADDR``): ``distributed.Client.map(...,
  retries=2, pure=False)`` (``submit`` of every task in one message) and
  ``as_completed``.  ``tcp://HOST:PORT`` joins a running
  scheduler (``dask scheduler`` / ``dask worker``, dask-kubernetes, dask-jobqueue,
  ``SSHCluster``; docs/scale-out.md); ``local:N`` starts a ``LocalCluster`` of N worker
  processes on 127.0.0.1 (dashboard off) and closes it afterwards.  A worker lost
  mid-batch has its tasks rerun by the scheduler on another worker.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Generic, Protocol, TypeVar

from rig.blas_threads import one_blas_thread

__all__ = ["MAX_LOCAL_WORKERS", "BatchError", "BatchExecutor", "BatchResult",
           "ClusterAddress", "ClusterAddressError", "ClusterError", "DaskExecutor",
           "LocalExecutor", "TaskFailure", "make_executor", "parse_cluster_address"]

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")

#: most worker processes of ``local:N`` (one machine)
MAX_LOCAL_WORKERS = 256
#: how long to wait for a scheduler to answer [s]
CONNECT_TIMEOUT_S = 10.0
#: times Dask reruns a task that raised (a worker lost mid-task is rerun by the scheduler
#: anyway, up to distributed's ``allowed-failures``)
RETRIES = 2

#: the scheduler's HTTP endpoints (health, metrics; the dashboard stays off) on a free
#: port of 127.0.0.1, not on 8787
LOCAL_HTTP = {"dashboard_address": "127.0.0.1:0"}

_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?)$")


class ClusterAddressError(ValueError):
    """A ``--cluster`` value that is neither ``tcp://HOST:PORT`` nor ``local:N``."""


class ClusterError(RuntimeError):
    """The Dask scheduler cannot be reached or the cluster cannot be started."""


@dataclass(frozen=True)
class ClusterAddress:
    """A parsed ``--cluster`` value: ``tcp`` (host, port) or ``local`` (workers)."""

    kind: str
    host: str = ""
    port: int = 0
    workers: int = 0

    def __str__(self) -> str:
        return f"local:{self.workers}" if self.kind == "local" else \
            f"tcp://{self.host}:{self.port}"


def parse_cluster_address(text: str) -> ClusterAddress:
    """``tcp://HOST:PORT`` (HOST a name, an IPv4 address or ``[IPv6]``; PORT 1..65535)
    or ``local:N`` (N in 1..:data:`MAX_LOCAL_WORKERS`); :class:`ClusterAddressError`
    naming what is wrong otherwise."""
    allowed = f"allowed tcp://HOST:PORT or local:N (N in 1..{MAX_LOCAL_WORKERS})"
    t = text.strip()
    if t.startswith("local:"):
        n = t[len("local:"):]
        if not n.isdigit() or not 1 <= int(n) <= MAX_LOCAL_WORKERS:
            raise ClusterAddressError(f"{text!r}: worker count {n!r} is not an integer in "
                                      f"1..{MAX_LOCAL_WORKERS}; {allowed}")
        return ClusterAddress("local", workers=int(n))
    if not t.startswith("tcp://"):
        raise ClusterAddressError(f"{text!r} is not a cluster address; {allowed}")
    rest = t[len("tcp://"):]
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not _HOST.match(host):
        raise ClusterAddressError(f"{text!r}: no valid HOST:PORT after tcp://; {allowed}")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ClusterAddressError(f"{text!r}: port {port!r} is not in 1..65535; {allowed}")
    return ClusterAddress("tcp", host=host, port=int(port))


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised (or whose worker was lost for good): its index in the batch,
    its case (what was run: plant, road, seed) and the error."""

    index: int
    case: str
    error: str

    def __str__(self) -> str:
        return f"task {self.index} ({self.case}): {self.error}"


class BatchError(RuntimeError):
    """Raised by :meth:`BatchResult.values` when tasks failed; ``failures`` lists them."""

    def __init__(self, desc: str, n_tasks: int, failures: Sequence[TaskFailure]) -> None:
        self.failures = list(failures)
        super().__init__(f"{desc}: {len(self.failures)} of {n_tasks} tasks failed: "
                         + "; ".join(str(f) for f in self.failures[:5])
                         + (" ..." if len(self.failures) > 5 else ""))


@dataclass
class BatchResult(Generic[R]):
    """Results in task order (None where the task failed) and the failures."""

    desc: str
    results: list[R | None]
    failures: list[TaskFailure] = field(default_factory=list)

    def values(self) -> list[R]:
        """Every result, in task order; :class:`BatchError` if any task failed."""
        if self.failures:
            raise BatchError(self.desc, len(self.results), self.failures)
        return [r for r in self.results if r is not None]


class BatchExecutor(Protocol):
    """Runs ``fn(shared, items[i])`` for every i and collects the results by index."""

    name: str

    @property
    def workers(self) -> int: ...

    def run(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T],
            cases: Sequence[str], *, desc: str = "batch", progress: bool = False,
            order: Sequence[int] | None = None) -> BatchResult[R]: ...

    def close(self) -> None: ...

    def __enter__(self) -> BatchExecutor: ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None: ...


def _one_blas_thread_then(fn: Callable[[S, T], R], shared: S, item: T) -> R:
    """A task on a Dask worker: the worker runs one BLAS thread, as a local worker does
    (rig.blas_threads: bit-identical results wherever a run is computed)."""
    one_blas_thread()
    return fn(shared, item)


def _identity(x: S) -> S:
    return x


def _error_text(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _bar(progress: bool, total: int, desc: str) -> Any:
    if not progress:
        return None
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="run")


def _check(items: Sequence[Any], cases: Sequence[str],
           order: Sequence[int] | None) -> list[int]:
    if len(cases) != len(items):
        raise ValueError(f"{len(items)} items but {len(cases)} cases")
    idx = list(range(len(items))) if order is None else list(order)
    if sorted(idx) != list(range(len(items))):
        raise ValueError("order must be a permutation of the task indices")
    return idx


class _ContextMixin:
    def close(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def __enter__(self: Any) -> Any:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class LocalExecutor(_ContextMixin):
    """``jobs`` local processes (default: every core); ``jobs == 1``: this process."""

    name = "local"

    def __init__(self, jobs: int | None = None) -> None:
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self._pool: ProcessPoolExecutor | None = None

    @property
    def workers(self) -> int:
        return self.jobs

    def run(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T],
            cases: Sequence[str], *, desc: str = "batch", progress: bool = False,
            order: Sequence[int] | None = None) -> BatchResult[R]:
        idx = _check(items, cases, order)
        res: BatchResult[R] = BatchResult(desc, [None] * len(items))
        bar = _bar(progress, len(items), desc)
        try:
            if self.jobs == 1 or len(items) <= 1:
                for i in idx:
                    try:
                        res.results[i] = fn(shared, items[i])
                    except Exception as exc:
                        res.failures.append(TaskFailure(i, cases[i], _error_text(exc)))
                    if bar is not None:
                        bar.update(1)
            else:
                if self._pool is None:
                    self._pool = ProcessPoolExecutor(max_workers=self.jobs,
                                                     initializer=one_blas_thread)
                futs: dict[Future[R], int] = {self._pool.submit(fn, shared, items[i]): i
                                              for i in idx}
                broken = False
                for fut in as_completed(futs):
                    i = futs[fut]
                    err = fut.exception()
                    if err is None:
                        res.results[i] = fut.result()
                    else:
                        broken |= isinstance(err, BrokenProcessPool)
                        res.failures.append(TaskFailure(i, cases[i], _error_text(err)))
                    if bar is not None:
                        bar.update(1)
                if broken:                 # a worker died: start a fresh pool next time
                    self._pool.shutdown(wait=False, cancel_futures=True)
                    self._pool = None
        finally:
            if bar is not None:
                bar.close()
        res.failures.sort(key=lambda f: f.index)
        return res

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(_ContextMixin):
    """The batch on a Dask distributed cluster (``address``: see the module docstring).
    Connects (or starts the ``local:N`` cluster) on construction; :class:`ClusterError`
    when that fails."""

    name = "dask"

    def __init__(self, address: ClusterAddress,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S) -> None:
        import logging

        from distributed import Client, LocalCluster
        self.address = address
        self._cluster: Any = None
        try:
            if address.kind == "local":
                self._cluster = LocalCluster(n_workers=address.workers, threads_per_worker=1,
                                             processes=True, host="127.0.0.1",
                                             dashboard_address=None,
                                             scheduler_kwargs=LOCAL_HTTP,
                                             silence_logs=logging.ERROR)
                self.client: Any = Client(self._cluster, timeout=f"{connect_timeout_s}s")
            else:
                self.client = Client(str(address), timeout=f"{connect_timeout_s}s")
            try:                       # a scheduler without workers would hang the batch
                self.client.wait_for_workers(1, timeout=connect_timeout_s)
            except TimeoutError:
                self.close()
                raise ClusterError(f"the Dask scheduler at {address} has no workers "
                                   f"(none joined within {connect_timeout_s:g} s)") from None
        except (OSError, TimeoutError, ValueError) as exc:
            if self._cluster is not None:
                self._cluster.close()
            raise ClusterError(f"cannot reach the Dask scheduler at {address}: "
                               f"{_error_text(exc)}") from None

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info().get("workers", {}))

    def run(self, fn: Callable[[S, T], R], shared: S, items: Sequence[T],
            cases: Sequence[str], *, desc: str = "batch", progress: bool = False,
            order: Sequence[int] | None = None) -> BatchResult[R]:
        from distributed import as_completed as dask_completed
        idx = _check(items, cases, order)
        res: BatchResult[R] = BatchResult(desc, [None] * len(items))
        if not items:
            return res
        # sent once and held by the scheduler as a task (not scattered data), so a worker
        # lost with its copy has it recomputed; each worker fetches it once, not per task
        shared_f = self.client.submit(_identity, shared, pure=False, retries=RETRIES)
        # one message for the whole batch; tasks start in ``order`` (submission order)
        futs = self.client.map(_one_blas_thread_then, [fn] * len(idx),
                               [shared_f] * len(idx), [items[i] for i in idx],
                               retries=RETRIES, pure=False)
        where = {f.key: i for f, i in zip(futs, idx, strict=True)}
        bar = _bar(progress, len(items), desc)
        try:
            for fut in dask_completed(futs):
                i = where[fut.key]
                if fut.status == "finished":
                    res.results[i] = fut.result()
                else:
                    try:
                        exc = fut.exception()
                        text = _error_text(exc) if exc is not None else fut.status
                    except Exception as err:      # cancelled / lost: no exception object
                        text = f"{fut.status}: {_error_text(err)}"
                    res.failures.append(TaskFailure(i, cases[i], text))
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
            self.client.cancel(futs)
            self.client.cancel([shared_f])
        res.failures.sort(key=lambda f: f.index)
        return res

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None


def make_executor(cluster: ClusterAddress | None = None,
                  jobs: int | None = None) -> BatchExecutor:
    """The executor for ``--cluster`` (None: :class:`LocalExecutor` with ``jobs``)."""
    if cluster is None:
        return LocalExecutor(jobs)
    return DaskExecutor(cluster)
