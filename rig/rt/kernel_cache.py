"""Keeps numba's on-disk cache of the runtime bank consistent with its sources.

numba checks only the defining file of a cached function, but ``bank_step`` compiles in
code and buffer offsets from several modules of :mod:`controller.runtime`.  Entry points
(the ``rig`` command line, the test session, the benchmarks) call
:func:`drop_stale_kernel_cache` before the bank is imported: when any of those sources
changed since the cache was written, the bank's cached kernels are removed and numba
compiles them again.  ``controller/`` itself does no file I/O.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import controller.runtime

__all__ = ["KERNEL_CONSTANT_SOURCES", "KERNEL_SOURCES", "drop_stale_kernel_cache"]

#: the sources compiled into the bank's step (controller/runtime/)
KERNEL_SOURCES = ("bank.py", "kernels.py", "layout.py", "moving_bank.py", "bayes.py",
                  "mass_layers.py")
#: sources outside controller/runtime/ whose constants the kernels compile in (the
#: sprung-mass estimator's and the wheel-hop tracker's parameter and state offsets, the
#: travel schedule's parameter count, the blending modes, the largest compute delay),
#: relative to it: every controller module the kernel sources other than bank.py import
#: from (tests/test_kernel_cache.py)
KERNEL_CONSTANT_SOURCES = ("../arrays.py", "../config.py", "../mass_estimator.py",
                           "../modes.py", "../travel_schedule.py", "../wheel_hop.py")
_STAMP = "bank_kernels.sha256"


def drop_stale_kernel_cache() -> bool:
    """Remove the bank's cached kernels if :data:`KERNEL_SOURCES` changed since they were
    cached; True when something was removed.  A read-only install is left alone (numba
    falls back to compiling in memory as usual)."""
    here = Path(controller.runtime.__file__).resolve().parent
    cache_dir = here / "__pycache__"
    try:
        blob = b"".join((here / f).read_bytes()
                        for f in (*KERNEL_SOURCES, *KERNEL_CONSTANT_SOURCES))
        digest = hashlib.sha256(blob).hexdigest()
        stamp = cache_dir / _STAMP
        if stamp.exists() and stamp.read_text() == digest:
            return False
        # every kernel of the package: the others compile in kernels.py's slot offsets too
        stale = [f for name in KERNEL_SOURCES
                 for f in cache_dir.glob(f"{name.removesuffix('.py')}.*.nb[ic]")]
        for f in stale:
            f.unlink(missing_ok=True)
        cache_dir.mkdir(exist_ok=True)
        stamp.write_text(digest)
        return bool(stale)
    except OSError:
        return False
