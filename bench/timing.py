"""Timing helper shared by the benchmarks."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any


def median_call_ns(fn: Callable[[], Any], n: int, batches: int) -> float:
    """Median over ``batches`` of the mean time of one call of ``fn`` in a batch of ``n``
    calls [ns] (the median of batch means resists another process taking the CPU)."""
    times = []
    for _ in range(batches):
        t0 = time.perf_counter_ns()
        for _ in range(n):
            fn()
        times.append((time.perf_counter_ns() - t0) / n)
    return statistics.median(times)
