"""The optional dependencies of the distribution (pyproject.toml,
``[project.optional-dependencies]``) that commands need at run time, and the one line a
command says when one is missing.

``export`` holds asammdf (``rig export --format mf4``; python-can's MF4 reader, so
``rig replay RUN.mf4``) and pyarrow (``--format parquet|csv``).  They stay out of the
base install because python-can imports its MF4 module, and with it asammdf and pandas,
at ``import can`` whenever asammdf is installed: ~0.4 s of start-up and ~100 MB of
memory (locked by the loop's real-time set-up) in every process that talks CAN.  With
asammdf absent python-can leaves MF4 out silently.  So the modules that need them import
them inside the functions that use them, after :func:`require`.
"""

from __future__ import annotations

import importlib
from typing import Final

__all__ = ["DISTRIBUTION", "EXPORT", "MissingExtraError", "require"]

#: the distribution's name (pyproject.toml ``project.name``; tests/test_extras.py)
DISTRIBUTION: Final = "lqg-fuzzy-rig"
#: the extra with the exporters' dependencies (pyproject.toml)
EXPORT: Final = "export"


class MissingExtraError(Exception):
    """A command needs a module of an extra that is not installed; the message says
    which and how to install it (``rig`` prints it as one line, exit status 2)."""


def require(module: str, extra: str, what: str) -> None:
    """Import ``module`` (of the extra ``extra``), or raise :class:`MissingExtraError` saying
    that ``what`` (e.g. "MF4 export") needs the extra."""
    try:
        importlib.import_module(module)
    except ImportError as exc:
        absent = isinstance(exc, ModuleNotFoundError) and exc.name == module
        why = f"{module} is not installed" if absent else f"{module} does not import: {exc}"
        raise MissingExtraError(f"{what} needs the '{extra}' extra ({why}): "
                           f"pip install '{DISTRIBUTION}[{extra}]'") from None
