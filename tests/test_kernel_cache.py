"""The stale-kernel-cache guard: controller/ does no file I/O at import, the entry
points drop the bank's cached kernels when a source they compile in changed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import controller.runtime
from rig.rt import kernel_cache

ROOT = Path(__file__).resolve().parents[1]


def test_importing_the_bank_writes_no_file(tmp_path: Path) -> None:
    """A fresh interpreter imports controller.runtime.bank with the cache guard's stamp
    absent: the import itself leaves no stamp (only entry points write it)."""
    code = ("import controller.runtime.bank, pathlib, controller.runtime as r; "
            "p = pathlib.Path(r.__file__).parent / '__pycache__' / 'bank_kernels.sha256'; "
            "print(p.exists())")
    stamp = Path(controller.runtime.__file__).parent / "__pycache__" / "bank_kernels.sha256"
    saved = stamp.read_text() if stamp.exists() else None
    try:
        stamp.unlink(missing_ok=True)
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                             text=True, check=True, timeout=300)
        assert out.stdout.strip() == "False"
    finally:
        if saved is not None:
            stamp.parent.mkdir(exist_ok=True)
            stamp.write_text(saved)


def test_changed_sources_drop_the_cached_kernels(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = tmp_path / "runtime"
    (pkg / "__pycache__").mkdir(parents=True)
    for name in kernel_cache.KERNEL_SOURCES:
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
