"""On-disk cache of designed banks: a configuration is designed once per machine and
code version, not at every start.

``rig run`` and ``rig demo`` without ``--design``, ``rig replay`` without an artifact,
the simulator, the Monte Carlo, the study and the tests design the bank for their
configuration (:func:`controller.design.design_bank`, seconds; more with the bank's
layers).  :func:`design_for` keeps each design as the versioned artifact
(:func:`controller.artifact.save_design`) under a key of

* the design sections' hash (:func:`controller.config.design_config_hash`, the
  artifact's own check: the arrays depend on those sections only), and
* a stamp of the code that designs: every source file of ``controller/``, the artifact
  version, and the numpy, scipy and python-control versions.

A hit's metadata is rebuilt for the asking configuration (:func:`build_metadata`: its
full hash and TOML, as ``design_bank`` writes them; ``created_utc`` stays the design's).
An entry is written under a temporary name and renamed, so a reader sees a whole file or
none; the least recently used entries beyond :data:`MAX_ENTRIES` are removed.  Anything
wrong with the cache (a directory that cannot be written, an entry that does not read
back) is logged once and the bank is designed as without it: the cache only saves time.

Directory: ``$RIG_DESIGN_CACHE`` (``off`` disables the cache), else systemd's
``$CACHE_DIRECTORY/designs`` (``CacheDirectory=`` of deploy/rig.service), else
``$XDG_CACHE_HOME/rig/designs``, else ``~/.cache/rig/designs``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import logging
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import controller

if TYPE_CHECKING:
    from controller.artifact import Design
    from controller.config import RigConfig

__all__ = ["ENV", "MAX_ENTRIES", "cache_dir", "code_stamp", "design_for"]

log = logging.getLogger(__name__)

#: the environment variable naming the directory (``off``: no cache)
ENV = "RIG_DESIGN_CACHE"
#: entries kept (about 2-5 MB each); the least recently used beyond it are removed
MAX_ENTRIES = 64
_warned: set[str] = set()


def cache_dir() -> Path | None:
    """The cache's directory (module docstring), or None when ``$RIG_DESIGN_CACHE`` is
    ``off``."""
    env = os.environ.get(ENV)
    if env:
        return None if env.strip().lower() == "off" else Path(env)
    systemd = os.environ.get("CACHE_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0]) / "designs"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "rig" / "designs"


@functools.cache
def code_stamp() -> str:
    """sha256 over every source of ``controller/`` (path and bytes), the artifact version
    and the numerical libraries' versions: what a design depends on besides its
    configuration."""
    import control
    import numpy as np
    import scipy

    from controller.artifact import ARTIFACT_VERSION

    root = Path(controller.__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0")
        h.update(f.read_bytes())
    h.update(f"artifact {ARTIFACT_VERSION} numpy {np.__version__} scipy {scipy.__version__} "
             f"control {control.__version__}".encode())
    return h.hexdigest()


def _warn_once(what: str, exc: BaseException) -> None:
    if what not in _warned:
        _warned.add(what)
        log.warning("design cache: %s (%s); designing without it", what, exc)


def design_for(cfg: RigConfig) -> Design:
    """The bank :func:`controller.design.design_bank` designs for ``cfg``, from the cache
    when it holds it (then with ``cfg``'s own metadata), else designed and stored."""
    import controller.design
    from controller.artifact import DesignMismatch, build_metadata, load_design, save_design
    from controller.config import design_config_hash

    d = cache_dir()
    if d is None:
        return controller.design.design_bank(cfg)
    key = hashlib.sha256(f"{design_config_hash(cfg)} {code_stamp()}".encode()).hexdigest()
    path = d / f"{key[:32]}.npz"
    try:
        design = load_design(path, cfg)             # checks the design sections' hash
    except FileNotFoundError:
        pass
    except (OSError, DesignMismatch) as exc:
        _warn_once(f"cannot read {path}", exc)
    else:
        with contextlib.suppress(OSError):
            os.utime(path)                                  # least recently used order
        log.info("bank design read from the design cache (%s)", path)
        metadata = {**build_metadata(cfg), "created_utc": design.metadata.get("created_utc")}
        return dataclasses.replace(design, metadata=metadata)
    design = controller.design.design_bank(cfg)
    try:
        d.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".design-", suffix=".tmp", dir=d)
        try:
            os.close(fd)
            save_design(design, tmp)
            os.replace(tmp, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        _prune(d)
    except OSError as exc:
        _warn_once(f"cannot write {d}", exc)
    return design


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except OSError:                                         # removed by another process
        return 0.0


def _prune(d: Path) -> None:
    entries = sorted(d.glob("*.npz"), key=_mtime, reverse=True)
    for old in entries[MAX_ENTRIES:]:
        with contextlib.suppress(OSError):
            old.unlink()
