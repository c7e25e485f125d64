"""Array type aliases shared by every layer (one owner for the dtype of a float array)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: a float64 NumPy array; shapes are documented where each is used
FloatArray = NDArray[np.float64]

__all__ = ["FloatArray"]
