"""Loop timing statistics without allocation on the hot path.

Two quantities per tick, both in integer nanoseconds:

- **lateness** (the jitter of a fixed-rate loop with absolute deadlines): wake-up time
  minus the tick's deadline, i.e. how late the tick started;
- **step time**: wake-up to the end of the tick's work (including CAN I/O).

Each is kept twice, in preallocated buffers (``array.array``, written per tick, with numpy
views of the same memory for the statistics): a ring of the last ``ring_size``
samples (recent behaviour, exact percentiles) and a whole-run histogram with 1 us bins
up to ``hist_max_us`` (overflow in the last bin; the exact maximum is kept aside).
:meth:`TimingStats.start_tick` / :meth:`TimingStats.end_tick` are O(1) and allocate
nothing but the Python ints they are given; percentiles are computed off the hot path
(:meth:`summary`), except the cheap :meth:`lateness_p99_us` used for the heartbeat,
which works in a preallocated buffer.
"""

from __future__ import annotations

import math
from array import array

import numpy as np

__all__ = ["RECENT_TICKS", "TimingStats", "histogram_percentile_us"]

#: ticks of skipped-deadline counts kept for :meth:`TimingStats.recent_window` (the
#: lateness itself is in the lateness ring)
RECENT_TICKS = 64


def histogram_percentile_us(hist: np.ndarray, q: float) -> float:
    """``q``-th percentile (0..100) of a 1-us-bin histogram, in us (bin lower edge)."""
    total = int(hist.sum())
    if total == 0:
        return float("nan")
    cum = np.cumsum(hist)
    rank = max(1, int(np.ceil(q / 100.0 * total)))
    return float(np.searchsorted(cum, rank, side="left"))


class TimingStats:
    """Ring buffers + histograms of lateness and step time; overrun and miss counts."""

    def __init__(self, period_ns: int, overrun_threshold_ns: int, *,
                 miss_threshold_ns: int = 500_000, ring_size: int = 1 << 16,
                 hist_max_us: int = 10_000) -> None:
        if period_ns <= 0 or ring_size <= 0 or hist_max_us <= 0:
            raise ValueError("period_ns, ring_size and hist_max_us must be positive")
        self.period_ns = int(period_ns)
        self.overrun_threshold_ns = int(overrun_threshold_ns)
        self.miss_threshold_ns = int(miss_threshold_ns)
        self.ring_size = int(ring_size)
        self.hist_max_us = int(hist_max_us)
        # the hot path writes the Python arrays (a fraction of numpy's cost per element);
        # the numpy attributes are views of the same memory, for the statistics
        self._lat = array("q", bytes(8 * ring_size))
        self._stp = array("q", bytes(8 * ring_size))
        self._lat_hist = array("q", bytes(8 * (hist_max_us + 1)))
        self._stp_hist = array("q", bytes(8 * (hist_max_us + 1)))
        self._skip = array("q", bytes(8 * RECENT_TICKS))
        self.lateness_ring = np.frombuffer(self._lat, dtype=np.int64)
        self.step_ring = np.frombuffer(self._stp, dtype=np.int64)
        self.lateness_hist = np.frombuffer(self._lat_hist, dtype=np.int64)
        self.step_hist = np.frombuffer(self._stp_hist, dtype=np.int64)
        self._cum = np.zeros(hist_max_us + 1, dtype=np.int64)
        #: deadlines skipped after each of the last RECENT_TICKS ticks (index: tick % size)
        self.recent_skipped = np.frombuffer(self._skip, dtype=np.int64)
        self.reset()

    def reset(self) -> None:
        self.lateness_ring[:] = 0
        self.step_ring[:] = 0
        self.lateness_hist[:] = 0
        self.step_hist[:] = 0
        self.recent_skipped[:] = 0
        self.count = 0
        self._ended = 0             # ticks whose end_tick ran
        self._index = 0
        self.max_lateness_ns = 0
        self.max_step_ns = 0
        self.overruns = 0           # ticks later than overrun_threshold_ns
        self.misses = 0             # ticks later than miss_threshold_ns
        self.skipped = 0            # deadlines skipped because the loop was > 1 period late
        self.overrun_streak = 0     # consecutive overrun ticks up to now

    # ------------------------------------------------------------------ hot path
    def start_tick(self, lateness_ns: int) -> None:
        """Record the lateness of the tick that starts now.  O(1)."""
        i = self._index
        self._lat[i] = lateness_ns
        b = lateness_ns // 1000
        top = self.hist_max_us
        self._lat_hist[0 if b < 0 else (b if b < top else top)] += 1
        if lateness_ns > self.max_lateness_ns:
            self.max_lateness_ns = lateness_ns
        if lateness_ns > self.overrun_threshold_ns:
            self.overruns += 1
            self.overrun_streak += 1
        else:
            self.overrun_streak = 0
        if lateness_ns > self.miss_threshold_ns:
            self.misses += 1
        self._skip[self.count % RECENT_TICKS] = 0
        self.count += 1

    def end_tick(self, step_ns: int) -> None:
        """Record the step time of the tick started by :meth:`start_tick`.  O(1)."""
        self._ended += 1
        i = self._index
        self._stp[i] = step_ns
        self._index = i + 1 if i + 1 < self.ring_size else 0
        b = step_ns // 1000
        top = self.hist_max_us
        self._stp_hist[0 if b < 0 else (b if b < top else top)] += 1
        if step_ns > self.max_step_ns:
            self.max_step_ns = step_ns

    def add(self, lateness_ns: int, step_ns: int) -> None:
        """Record one whole tick (both halves)."""
        self.start_tick(lateness_ns)
        self.end_tick(step_ns)

    def add_skipped(self, n: int) -> None:
        """``n`` deadlines were skipped after the last tick (a stall)."""
        self.skipped += n
        if self.count:
            self.recent_skipped[(self.count - 1) % RECENT_TICKS] += n

    def lateness_p99_us(self) -> float:
        """Whole-run p99 lateness from the histogram, in a preallocated buffer (us)."""
        if self.count == 0:
            return 0.0
        np.cumsum(self.lateness_hist, out=self._cum)
        rank = -(-99 * self.count // 100)
        return float(np.searchsorted(self._cum, rank, side="left"))

    # ------------------------------------------------------------------ off the hot path
    def recent_window(self, ticks: int) -> tuple[int, int, int]:
        """The loop's lateness over its last ``ticks`` ticks (the current one included,
        at most ``min(RECENT_TICKS, ring_size)``): ``(max_late_ns, ago, skipped)`` -- the
        worst wake-up lateness (a stall shows as one late wake-up, the deadlines it
        swallowed are then skipped), how many ticks before the current one it was, and
        the deadlines skipped after the window's ticks.  For fault attribution (rare):
        may allocate."""
        n = max(0, min(int(ticks), self.count, RECENT_TICKS, self.ring_size))
        if n == 0:
            return 0, 0, 0
        # the current tick's lateness is at _index while its end_tick has not run yet
        newest = self._index if self.count > self._ended else self._index - 1
        back = np.arange(n)
        late = self.lateness_ring[(newest - back) % self.ring_size]
        skipped = int(self.recent_skipped[(self.count - 1 - back) % RECENT_TICKS].sum())
        ago = int(np.argmax(late))
        return int(late[ago]), ago, skipped

    def recent(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the last min(count, ring_size) samples, oldest first (ns)."""
        n = min(self.count, self.ring_size)
        if self.count <= self.ring_size:
            return self.lateness_ring[:n].copy(), self.step_ring[:n].copy()
        i = self._index
        return (np.concatenate((self.lateness_ring[i:], self.lateness_ring[:i])),
                np.concatenate((self.step_ring[i:], self.step_ring[:i])))

    def summary(self) -> dict[str, float | int]:
        """Whole-run percentiles (us, 1 us resolution), maxima and counts."""
        out: dict[str, float | int] = {"ticks": self.count}
        for name, hist, mx in (("lateness", self.lateness_hist, self.max_lateness_ns),
                               ("step", self.step_hist, self.max_step_ns)):
            # one cumulative sum per histogram for its three percentiles (the status
            # thread calls this every 0.2 s while holding the interpreter lock)
            cum = np.cumsum(hist)
            total = int(cum[-1])
            for q, label in ((50.0, "p50"), (99.0, "p99"), (99.9, "p99_9")):
                out[f"{name}_{label}_us"] = (
                    float(np.searchsorted(cum, max(1, math.ceil(q / 100.0 * total)),
                                          side="left")) if total else math.nan)
            out[f"{name}_max_us"] = mx / 1000.0 if self.count else float("nan")
        out["overruns"] = self.overruns
        out["misses"] = self.misses
        out["skipped"] = self.skipped
        return out
