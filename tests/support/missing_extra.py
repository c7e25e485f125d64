"""A Python without the ``export`` extra, simulated in a child process: a
``sitecustomize`` puts a finder first on ``sys.meta_path`` that answers every import of
asammdf, pyarrow and pandas (and their submodules) with ``ModuleNotFoundError``, as an
install without them would, and counts the attempts (``sys.blocked_imports``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Final

#: the top-level modules the extra brings (pandas: asammdf's dependency)
BLOCKED: Final = ("asammdf", "pyarrow", "pandas")

SITECUSTOMIZE: Final = f'''
import sys

BLOCKED = frozenset({BLOCKED!r})
sys.blocked_imports = []


class _WithoutExportExtra:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            sys.blocked_imports.append(name)
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, _WithoutExportExtra())
'''


def without_export_env(tmp: Path) -> dict[str, str]:
    """The environment of a child process that runs as if the extra were not installed
    (its ``sitecustomize`` written to ``tmp``)."""
    site = tmp / "without-export-extra"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(site), env.get("PYTHONPATH")) if p)
    return env


def run_without_export(tmp: Path, *args: str, cwd: Path | None = None,
                       timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """``python ARGS`` without the extra."""
    return subprocess.run([sys.executable, *args], env=without_export_env(tmp), cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)
