"""A token bucket: at most ``burst`` at once, refilled at ``rate_per_s`` (thread-safe), and
one bucket per peer (:class:`PeerBuckets`).  The clock is injectable (tests count, they
do not sleep)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

__all__ = ["MAX_PEERS", "OVERFLOW_PEER", "PeerBuckets", "TokenBucket"]


class TokenBucket:
    """:meth:`take` is True while tokens are left; :attr:`refused` counts the others."""

    def __init__(self, rate_per_s: float, burst: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if rate_per_s <= 0 or burst < 1:
            raise ValueError(f"rate {rate_per_s} / burst {burst}: must be > 0 / >= 1")
        self.rate_per_s = float(rate_per_s)
        self.burst = int(burst)
        self._clock = clock
        self._tokens = float(burst)
        self._last = clock()
        self._lock = threading.Lock()
        self.refused = 0

    def take(self) -> bool:
        with self._lock:
            now = self._clock()
            self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate_per_s)
            self._last = now
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                return True
            self.refused += 1
            return False


#: peers remembered by a :class:`PeerBuckets`; more share one bucket (``OVERFLOW_PEER``)
MAX_PEERS = 256
OVERFLOW_PEER = "(other peers)"


class PeerBuckets:
    """One :class:`TokenBucket` per peer (at most :data:`MAX_PEERS`; further peers share
    the bucket of :data:`OVERFLOW_PEER`), so that one peer flooding cannot use up what the
    others get; :attr:`refused` counts per peer (thread-safe)."""

    def __init__(self, rate_per_s: float, burst: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        TokenBucket(rate_per_s, burst, clock)          # the same checks, at construction
        self.rate_per_s = float(rate_per_s)
        self.burst = int(burst)
        self._clock = clock
        self._buckets: dict[str, TokenBucket] = {}
        self._lock = threading.Lock()

    def take(self, peer: str) -> bool:
        with self._lock:
            bucket = self._buckets.get(peer)
            if bucket is None:
                if len(self._buckets) >= MAX_PEERS:
                    peer = OVERFLOW_PEER
                    bucket = self._buckets.get(peer)
                if bucket is None:
                    bucket = self._buckets[peer] = TokenBucket(self.rate_per_s, self.burst,
                                                               self._clock)
        return bucket.take()

    @property
    def refused(self) -> dict[str, int]:
        """Refusals per peer (peers with none left out)."""
        with self._lock:
            return {p: b.refused for p, b in self._buckets.items() if b.refused}
