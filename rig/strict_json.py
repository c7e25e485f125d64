"""Strict JSON for every ``rig ... --json``: what the commands print parses with any JSON
parser (RFC 8259), which has no NaN or Infinity.

A non-finite float (NaN, +inf, -inf) is printed as ``null``: "no finite value" (a ratio
over a zero, a metric of an empty half, the continuous frequency of a pole at z = 0).
NumPy scalars and arrays become numbers and lists, tuples lists, mapping keys strings;
anything else (paths, enums...) its ``str``.  :func:`dumps` then serialises with
``allow_nan=False``, so a value this conversion missed fails loudly instead of printing
invalid JSON.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

__all__ = ["dumps", "json_lines", "jsonable"]


def jsonable(obj: Any) -> Any:
    """A copy of ``obj`` made of JSON types only, non-finite floats as None."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [jsonable(v) for v in obj.tolist()]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, bool | int | str):
        return obj
    if isinstance(obj, complex):
        return jsonable([obj.real, obj.imag])
    return str(obj)


def dumps(obj: Any, *, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see the module docstring)."""
    return json.dumps(jsonable(obj), indent=indent, allow_nan=False)


def json_lines(lines: Iterable[bytes | str]) -> Iterator[dict[str, Any]]:
    """The JSON objects among ``lines`` (a child process's status stream): lines that are
    not a JSON object (a stray print, a partial line at exit) are skipped."""
    for line in lines:
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if isinstance(obj, dict):
            yield obj
