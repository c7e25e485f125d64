"""Where test code lives: test modules share helpers through ``tests/support/`` and
``tests/conftest.py`` only, never by importing another test module or a helper from
``bench/`` (``tests/test_protocol.py`` runs ``bench/codec_bench.py`` once, by path, to
check the benchmark itself), and the benchmarks do not edit ``sys.path``."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imported_modules(path: Path) -> list[str]:
    """Every module ``path`` imports (absolute names; relative imports resolved as
    written, i.e. without the package)."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module is not None:
            names.append(node.module)
    return names


def _forbidden(module: str) -> bool:
    """A test module (``tests[.pkg].test_*``) or anything of ``bench``."""
    top, *rest = module.split(".")
    return top == "bench" or (top == "tests" and any(p.startswith("test_") for p in rest))


def test_tests_import_no_test_module_and_nothing_from_bench() -> None:
    offenders = [f"{p.relative_to(ROOT)}: {m}"
                 for p in sorted((ROOT / "tests").rglob("*.py"))
                 for m in _imported_modules(p) if _forbidden(m)]
    assert offenders == []


def test_the_rule_catches_both_kinds() -> None:
    assert _forbidden("tests.test_loop") and _forbidden("bench.replay_bench")
    assert _forbidden("bench")
    assert _forbidden("tests.socketcan.test_smoke_vcan")
    assert not _forbidden("tests.support.loop_harness") and not _forbidden("tests.socketcan")
    assert not _forbidden("hil.stepped_run")


def test_benchmarks_do_not_edit_sys_path() -> None:
    offenders = [str(p.relative_to(ROOT)) for p in sorted((ROOT / "bench").rglob("*.py"))
                 if "sys.path" in p.read_text()]
    assert offenders == []
