"""Fresh copies of a runtime bank's packed buffers, for tests that drive one kernel."""

from __future__ import annotations

import numpy as np

from controller.runtime.bank import BankRuntime

__all__ = ["fresh_buffers"]


def fresh_buffers(rt: BankRuntime) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``rt``'s parameter and state buffers (``fv``, ``iv``) after a reset."""
    rt.reset()
    return rt._fv.copy(), rt._iv.copy()
