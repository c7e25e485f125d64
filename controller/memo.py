"""A small per-process memo of things built from a configuration (a design, a road
preview's predictor): keyed by a hash of the configuration sections they read, the
oldest dropped first."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

__all__ = ["MEMO_SIZE", "memoised"]

T = TypeVar("T")

#: configurations each memo keeps (the oldest goes first)
MEMO_SIZE = 8


def memoised(store: dict[str, T], key: str, make: Callable[[], T]) -> T:
    """``store[key]``, made by ``make()`` the first time; at most :data:`MEMO_SIZE`
    kept."""
    if key not in store:
        if len(store) >= MEMO_SIZE:
            store.pop(next(iter(store)))
        store[key] = make()
    return store[key]
