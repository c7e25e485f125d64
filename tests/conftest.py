"""Fixtures shared by the test modules.  Test-only helpers live in ``tests/support/``."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from rig.blas_threads import one_blas_thread

one_blas_thread()  # before numpy loads its BLAS: as in every process `rig` starts

import pytest  # noqa: E402

from controller.artifact import Design, save_design  # noqa: E402
from controller.config import default_config  # noqa: E402
from rig.rt.kernel_cache import drop_stale_kernel_cache  # noqa: E402

# before any test module imports the runtime bank (numba's on-disk cache of its kernels)
drop_stale_kernel_cache()

from tests.support.loop_harness import LoopHarness, make_harness  # noqa: E402

if TYPE_CHECKING:
    from controller.runtime.bank import BankRuntime


def pytest_configure(config: pytest.Config) -> None:
    """One on-disk design cache (rig.design_cache) for the session: its xdist workers and
    every process they start design a configuration once; a fresh directory per session
    (``RIG_DESIGN_CACHE`` set beforehand is kept: a developer's own cache)."""
    from rig.design_cache import ENV

    if not hasattr(config, "workerinput") and ENV not in os.environ:
        path = tempfile.mkdtemp(prefix="rig-design-cache-")
        os.environ[ENV] = path
        config.stash[_CACHE_KEY] = path


def pytest_unconfigure(config: pytest.Config) -> None:
    path = config.stash.get(_CACHE_KEY, None)
    if path is not None:
        shutil.rmtree(path, ignore_errors=True)


_CACHE_KEY = pytest.StashKey[str]()


@pytest.fixture(scope="session")
def default_design() -> Design:
    """The bank designed from the built-in defaults (cached per process)."""
    from hil.sim.closed_loop import cached_design  # imports the bank: after the check

    return cached_design(default_config())


@pytest.fixture(scope="session")
def default_runtime(default_design: Design) -> BankRuntime:
    """A runtime bank of :func:`default_design` (tests reset it or copy its buffers:
    tests.support.bank_buffers)."""
    from controller.runtime.bank import BankRuntime

    return BankRuntime(default_design, cfg=default_config())


@pytest.fixture(scope="session")
def design_path(tmp_path_factory: pytest.TempPathFactory, default_design: Design) -> Path:
    """:func:`default_design` saved as an artifact file (``rig run --design``); a module
    that needs another configuration's design defines its own ``design_path``."""
    path = tmp_path_factory.mktemp("design") / "design.npz"
    save_design(default_design, path)
    return path


@pytest.fixture(scope="session")
def identification_run(tmp_path_factory: pytest.TempPathFactory, design_path: Path) -> Path:
    """An identification run (``tests/support/identify_run.py``), recorded once."""
    from tests.support.identify_run import record_identification_run

    path = tmp_path_factory.mktemp("identify") / "ex.mcap"
    return record_identification_run(path, design_path.read_bytes())


@pytest.fixture
def armed() -> Iterator[LoopHarness]:
    """A controller loop on a virtual bus (tests.support.loop_harness), armed: ten ticks,
    arm, one more tick, and its valve command enabled."""
    h = make_harness()
    h.run(10)
    h.arm()
    h.step()
    assert h.rig.valve[-1].enable == 1
    yield h
    h.close()
