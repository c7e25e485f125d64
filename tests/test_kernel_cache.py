"""The stale-kernel-cache guard: controller/ does no file I/O at import, the entry
points drop the bank's cached kernels when a source they compile in changed."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import controller.runtime
from rig.rt import kernel_cache

ROOT = Path(__file__).resolve().parents[1]


def test_importing_the_bank_writes_no_file(tmp_path: Path) -> None:
    """A fresh interpreter imports controller.runtime.bank with the cache guard's stamp
    absent: the import itself leaves no stamp (only entry points write it).

    The interpreter imports a copy of ``controller/`` made for this test: the source
    tree's ``__pycache__`` is shared with the other xdist worker, whose entry points write
    the stamp there at any moment."""
    shutil.copytree(ROOT / "controller", tmp_path / "controller",
                    ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import controller.runtime.bank, pathlib, controller.runtime as r; "
            "p = pathlib.Path(r.__file__).parent; "
            "print(p); print((p / '__pycache__' / 'bank_kernels.sha256').exists())")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                         capture_output=True, text=True, check=True, timeout=300)
    imported_from, stamp_written = out.stdout.split()
    assert Path(imported_from) == tmp_path / "controller" / "runtime"
    assert stamp_written == "False"


def test_changed_sources_drop_the_cached_kernels(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = tmp_path / "runtime"
    (pkg / "__pycache__").mkdir(parents=True)
    for name in (*kernel_cache.KERNEL_SOURCES, *kernel_cache.KERNEL_CONSTANT_SOURCES):
        (pkg / name).write_text(f"# {name}\n")
    (pkg / "__init__.py").write_text("")
    monkeypatch.setattr(controller.runtime, "__file__", str(pkg / "__init__.py"))
    cached = pkg / "__pycache__" / "bank.bank_step-1.py311.nbi"
    cached.write_text("x")
    assert kernel_cache.drop_stale_kernel_cache() is True       # no stamp yet: dropped
    assert not cached.exists()
    cached.write_text("x")
    assert kernel_cache.drop_stale_kernel_cache() is False      # unchanged: kept
    assert cached.exists()
    moving = pkg / "__pycache__" / "moving_bank.supervise-1.py311.nbc"
    moving.write_text("x")      # compiled in kernels.py's slot offsets: dropped as well
    (pkg / "layout.py").write_text("# changed\n")
    assert kernel_cache.drop_stale_kernel_cache() is True
    assert not cached.exists() and not moving.exists()
    cached.write_text("x")      # the estimator's offsets are compiled into the kernels
    (tmp_path / "mass_estimator.py").write_text("# changed\n")
    assert kernel_cache.drop_stale_kernel_cache() is True
    assert not cached.exists()


def test_every_module_the_kernels_import_from_is_a_source_of_the_stamp() -> None:
    """A constant the kernels compile in from outside controller/runtime/ (a slot
    offset, an enum) must change the stamp when its module changes, or numba keeps the
    kernel compiled with the old value: every ``controller.*`` module the kernel sources
    import from (bank.py's Python side aside: its kernels use the listed ones) is in
    KERNEL_CONSTANT_SOURCES."""
    here = Path(controller.runtime.__file__).resolve().parent
    listed = {Path(f).name for f in kernel_cache.KERNEL_CONSTANT_SOURCES}
    for name in kernel_cache.KERNEL_SOURCES:
        if name == "bank.py":
            continue
        tree = ast.parse((here / name).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and \
                    node.module.startswith("controller.") and \
                    not node.module.startswith("controller.runtime"):
                assert node.module.split(".")[1] + ".py" in listed, (name, node.module)
