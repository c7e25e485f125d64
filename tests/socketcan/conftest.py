"""The real-SocketCAN suite: runs only where vcan0 exists (``bash tests/socketcan/run.sh``).

On a machine without vcan0 (a plain ``pytest tests/``) every test here is reported as
skipped with the reason; run.sh runs them natively or inside user-mode-linux.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.socketcan.support import CHANNEL, MEASUREMENTS, Children, vcan_status

_HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    usable, reason = vcan_status(CHANNEL)
    skip = pytest.mark.skip(reason=f"SocketCAN suite: {reason}")
    for item in items:
        if _HERE in Path(str(item.path)).resolve().parents:
            item.add_marker(pytest.mark.socketcan)
            if not usable:
                item.add_marker(skip)


@pytest.fixture
def channel() -> str:
    return CHANNEL


@pytest.fixture
def children(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Children]:
    """Child processes of one test; all stopped by PID at teardown, logs shown on failure."""
    kids = Children(tmp_path)
    yield kids
    kids.stop_all()
    report = getattr(request.node, "rep_call", None)
    if report is not None and report.failed:
        print("\n".join(kids.dump()))


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    rep = yield
    setattr(item, f"rep_{rep.when}", rep)
    return rep


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if not MEASUREMENTS:
        return
    terminalreporter.section(f"SocketCAN measurements ({CHANNEL}, {_environment()})")
    for name, (value, unit, note) in MEASUREMENTS.items():
        terminalreporter.write_line(f"{name:<44} {value:>12.6g} {unit:<8} {note}")


def _environment() -> str:
    kernel = os.uname().release
    return f"user-mode-linux {kernel}" if os.environ.get("SOCKETCAN_IN_UML") else kernel
