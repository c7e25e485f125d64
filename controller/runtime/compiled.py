"""A numba function called without numba's per-call dispatch.

A call through a numba dispatcher first works out the numba type of every argument and
looks the compiled version up by them: about 0.1 µs an array argument; the previewed
step with its 14 arrays took 5.1 µs a call back to back through the dispatcher, 3.8 µs
through the entry point (docs/design.md §12).  A
function compiled for one explicit signature has one compiled version, whose entry
point (``dispatcher.overloads[signature].entry_point``) takes the same arguments and
skips that look-up.  It does not check the arguments' types: an array of another
dtype, number of dimensions or layout would be read as if it had the signature's, and
a number is taken as Python's ``float()`` / ``int()`` takes it (a string ``"1"`` too,
which the dispatcher refuses).  So :func:`direct_call` hands out the entry point only
for arguments whose types it has checked against the signature: the caller passes
those same arrays (its own, or ones it checks again when they change) and numbers of
exactly Python's ``float`` / ``int`` (checked each call, ``type(x) is float``: 30 ns);
anything else takes the dispatcher, which raises ``TypeError`` on a mismatch.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numba as nb
import numpy as np

__all__ = ["args_match", "direct_call"]


def _fits(arg: Any, t: Any) -> bool:
    if isinstance(arg, np.ndarray):
        return bool(nb.typeof(arg) == t)
    if t == nb.float64:
        return type(arg) is float
    if t == nb.int64:
        return type(arg) is int
    return False


def args_match(dispatcher: Any, args: Sequence[Any]) -> bool:
    """Whether ``args`` fit the one signature ``dispatcher`` was compiled for: as many
    as it has, every NumPy array of exactly the signature's numba type there (dtype,
    dimensions, C layout, writeable), every float64 a Python ``float`` and every int64
    a Python ``int`` (no other argument types)."""
    sigs = dispatcher.signatures
    if len(sigs) != 1 or len(sigs[0]) != len(args):
        return False
    return all(_fits(a, t) for a, t in zip(args, sigs[0], strict=True))


def direct_call(dispatcher: Any, args: Sequence[Any]) -> Callable[..., Any]:
    """The compiled entry point of ``dispatcher`` (a function compiled for one explicit
    signature) when ``args``, an example call's arguments, fit that signature
    (:func:`args_match`); else ``dispatcher`` itself.  Either is called like
    ``dispatcher``; the entry point only with the arrays checked here (or others of
    their types) and numbers of exactly the types checked here."""
    if not args_match(dispatcher, args):
        return dispatcher
    return dispatcher.overloads[dispatcher.signatures[0]].entry_point
