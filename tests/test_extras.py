"""The ``export`` extra (rig/extras.py): asammdf and pyarrow stay out of the base
install and out of the processes that talk CAN (python-can imports asammdf, and with it
pandas, at ``import can`` whenever it is installed), and without the extra the commands
that need it say so in one line, exit status 2 (tests/support/missing_extra.py)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from rig.export.stream import WRITER_MODULES
from rig.extras import DISTRIBUTION, EXPORT
from tests.support.missing_extra import BLOCKED, run_without_export

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

pytestmark = pytest.mark.timeout(300)


def _names(requirements: list[str]) -> set[str]:
    return {re.split(r"[\s<>=!~;\[]", r, maxsplit=1)[0].lower() for r in requirements}


def test_the_extra_is_declared_and_the_base_lacks_it() -> None:
    project = PYPROJECT["project"]
    assert project["name"] == DISTRIBUTION
    extra = _names(project["optional-dependencies"][EXPORT])
    assert {"asammdf", "pyarrow"} <= extra
    assert {m for m, _ in WRITER_MODULES.values()} <= extra
    assert not extra & _names(project["dependencies"])
    # the Dockerfile installs `project.dependencies` (the service alone), the Makefile
    # the dev venv with the extra
    assert '["project"]["dependencies"]' in (ROOT / "Dockerfile").read_text()
    assert re.search(r"^EXTRAS \?= .*\bexport\b", (ROOT / "Makefile").read_text(), re.M)


LOOP_PROCESS_IMPORTS = """
import json, sys
import can
import can.io.mf4
import rig.service.runner, hil.rig_process, rig.cli
import rig.commands.run, rig.commands.hil, rig.commands.demo
import rig.commands.export, rig.commands.replay, rig.export.stream, rig.replay
print(json.dumps({
    "loaded": sorted({m.partition(".")[0] for m in sys.modules} & set(BLOCKED)),
    "blocked": sys.blocked_imports,
    "mf4_reader": can.io.mf4.asammdf is not None,
}))
"""


def test_the_loop_processes_import_without_the_extra(tmp_path: Path) -> None:
    """The service, the emulated rig and every command module import with asammdf,
    pyarrow and pandas absent; python-can tries asammdf (the block is in effect) and
    leaves its MF4 module out without a word on stderr."""
    proc = run_without_export(tmp_path, "-c",
                              f"BLOCKED = {BLOCKED!r}\n{LOOP_PROCESS_IMPORTS}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr == ""
    got = json.loads(proc.stdout)
    assert got["loaded"] == [] and not got["mf4_reader"]
    assert "asammdf" in got["blocked"]


def test_rig_imports_the_writers_only_to_write() -> None:
    """With the extra installed, the CLI and the export modules still import neither
    asammdf nor pyarrow (they are imported in the functions that write)."""
    code = ("import sys, rig.cli, rig.commands.export, rig.export.stream, rig.export\n"
            "print(sorted({m.partition('.')[0] for m in sys.modules} "
            "& {'asammdf', 'pyarrow', 'pandas', 'can'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() == "[]"


def _one_line(proc: subprocess.CompletedProcess[str], expected: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-3000:])
    assert proc.stdout == ""
    assert proc.stderr == expected + "\n", proc.stderr[-3000:]


@pytest.mark.parametrize(("fmt", "out", "module", "what"), [
    ("mf4", "o.mf4", "asammdf", "MF4 export"),
    ("parquet", "o-parquet", "pyarrow", "Parquet export"),
    ("csv", "o-csv", "pyarrow", "CSV export"),
])
def test_export_without_the_extra_says_one_line(tmp_path: Path, fmt: str, out: str,
                                                module: str, what: str) -> None:
    work = tmp_path / "work"
    work.mkdir()
    (work / "run.mcap").write_bytes(b"\x89MCAP0\r\n")   # the check comes before any read
    proc = run_without_export(tmp_path, "-m", "rig.cli", "export", "run.mcap",
                              "--format", fmt, "--out", out, cwd=work)
    _one_line(proc, f"rig export: {what} needs the 'export' extra ({module} is not "
                    f"installed): pip install 'lqg-fuzzy-rig[export]'")
    assert sorted(p.name for p in work.iterdir()) == ["run.mcap"]     # nothing written


def test_replay_of_an_mf4_log_without_the_extra_says_one_line(tmp_path: Path) -> None:
    (tmp_path / "x.mf4").write_bytes(b"MDF     4.10    ")
    proc = run_without_export(tmp_path, "-m", "rig.cli", "replay", str(tmp_path / "x.mf4"))
    _one_line(proc, "rig replay: replaying an MF4 log needs the 'export' extra (asammdf is "
                    "not installed): pip install 'lqg-fuzzy-rig[export]'")
