"""No module of the project shadows a standard-library module: a process started from a
script inside a package (the recording writer, the rig process) has that package's folder
first on ``sys.path``, where ``operator.py`` would replace the standard ``operator``."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_no_module_is_named_like_a_standard_library_module() -> None:
    clashes = [str(p.relative_to(ROOT)) for pkg in ("controller", "rig", "hil")
               for p in (ROOT / pkg).rglob("*.py")
               if p.stem in sys.stdlib_module_names]
    assert clashes == []
