"""Test-only batch tasks for ``hil.batch`` (module-level, so workers can unpickle them;
tests/test_batch.py also registers this module to be pickled by value)."""

from __future__ import annotations

import os
from pathlib import Path


def square_or_raise(offset: int, x: int) -> int:
    """``(x + offset)^2``; raises for x == 3 (a task that fails)."""
    if x == 3:
        raise ValueError(f"task input {x} is refused")
    return (x + offset) ** 2


def die_once(flag_dir: str, x: int) -> int:
    """Kills its worker process the first time it sees ``x == 1`` (a flag file in
    ``flag_dir`` records that it did); the rerun returns ``10 x``."""
    flag = Path(flag_dir) / f"died-{x}"
    if x == 1 and not flag.exists():
        flag.write_text(str(os.getpid()))
        os._exit(3)
    return 10 * x


def pid(_shared: object, _x: int) -> int:
    """The worker's process id."""
    return os.getpid()
