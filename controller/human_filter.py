"""Human-body response filter F(s) (thesis Eq. 2.2-2.4): state space and ZOH discretisation.

F(s) = (b1 s + b0) / (s^2 + a1 s + a0), default 12 s / (s^2 + 30.02 s + 901.3), is
realised in controllable canonical form

    xf' = Af xf + Bf a,     y_f = Cf xf,     Af = [[0, 1], [-a0, -a1]], Bf = [0, 1],
    Cf = [b0, b1]

with a the sprung-mass acceleration [m/s^2] (the filter is strictly proper, Df = 0).
At run time its two states are *computed* from the measured acceleration with the
ZOH-discretised filter xf[k+1] = Ad xf[k] + Bd a[k]; they are not estimated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from controller.arrays import FloatArray
from controller.config import DesignConfig

__all__ = ["HumanFilter", "discretize_zoh", "human_filter"]


@dataclass(frozen=True)
class HumanFilter:
    """Continuous F(s) (Af, Bf, Cf) and its ZOH discretisation (Ad, Bd, Cd) at ``dt_s``."""

    Af: FloatArray
    Bf: FloatArray
    Cf: FloatArray
    dt_s: float
    Ad: FloatArray
    Bd: FloatArray

    @property
    def Cd(self) -> FloatArray:
        return self.Cf


def discretize_zoh(A: FloatArray, B: FloatArray, dt_s: float) -> tuple[FloatArray, FloatArray]:
    """Exact ZOH discretisation: (e^{A dt}, int_0^dt e^{A s} ds B) via one block exponential.

    ``B`` may be a vector (n,) or a matrix (n, m); the result has the same shape.
    """
    n = A.shape[0]
    Bm = B.reshape(n, -1)
    m = Bm.shape[1]
    blk = np.zeros((n + m, n + m))
    blk[:n, :n] = A
    blk[:n, n:] = Bm
    E = scipy.linalg.expm(blk * dt_s)
    return E[:n, :n], E[:n, n:].reshape(B.shape)


def human_filter(design: DesignConfig, dt_s: float) -> HumanFilter:
    """Build F(s) from ``design.human_filter_num`` / ``_den`` (highest power first)."""
    den = np.asarray(design.human_filter_den, dtype=float)
    num = np.asarray(design.human_filter_num, dtype=float)
    if den.shape != (3,) or den[0] == 0.0:
        raise ValueError(f"human filter denominator {den.tolist()} is not 2nd order")
    if num.shape[0] > 2:
        raise ValueError(f"human filter numerator {num.tolist()} is not strictly proper")
    num = np.concatenate([np.zeros(2 - num.shape[0]), num]) / den[0]
    a1, a0 = den[1] / den[0], den[2] / den[0]
    Af = np.array([[0.0, 1.0], [-a0, -a1]])
    Bf = np.array([0.0, 1.0])
    Cf = np.array([num[1], num[0]])
    Ad, Bd = discretize_zoh(Af, Bf, dt_s)
    return HumanFilter(Af, Bf, Cf, float(dt_s), Ad, Bd)
