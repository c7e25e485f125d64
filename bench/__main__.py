"""``python -m bench [--quick] [--json FILE] [NAME ...]``: run the benchmark modules.

Discovers ``bench/*_bench.py`` (sorted by file name).  A module takes part if it has
``run(quick: bool = False) -> list[dict]``; it may also define ``NAME`` (default: the
file name without ``_bench``), ``TITLE``, ``format_table(rows) -> str`` (default: a
generic table of the row dicts) and ``notes(rows) -> list[str]`` (printed under a
generic table).  ``NAME ...`` selects modules; a module that raises is reported and
the exit status is 1, the others still run.  ``--json FILE`` writes every row.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import sys
import time
import traceback
from pathlib import Path
from types import ModuleType
from typing import Any

from rig.rt.kernel_cache import drop_stale_kernel_cache

BENCH_DIR = Path(__file__).resolve().parent
ROOT = BENCH_DIR.parent



def discover() -> list[tuple[str, str]]:
    """(NAME, module path) of every ``*_bench.py`` module, sorted by file name."""
    out = []
    for path in sorted(BENCH_DIR.glob("*_bench.py")):
        out.append((path.stem.removesuffix("_bench"), f"bench.{path.stem}"))
    return out


def generic_table(rows: list[dict[str, Any]]) -> str:
    """A plain table of the rows' keys (in first-seen order); floats with 4 significant
    digits."""
    if not rows:
        return "(no rows)"
    cols: list[str] = []
    for r in rows:
        cols.extend(k for k in r if k not in cols)

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    cells = [[fmt(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)


def run_module(mod: ModuleType, quick: bool) -> list[dict[str, Any]]:
    run = mod.run
    params = inspect.signature(run).parameters
    rows: list[dict[str, Any]] = run(quick=quick) if "quick" in params else run()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
    ap.add_argument("names", nargs="*", help="modules to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="fewer samples (smoke run)")
    ap.add_argument("--json", metavar="FILE", help="also write all rows as JSON")
    args = ap.parse_args(argv)
    drop_stale_kernel_cache()
    found = discover()
    known = {name for name, _ in found}
    unknown = [n for n in args.names if n not in known]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; available: {sorted(known)}", file=sys.stderr)
        return 2
    status = 0
    everything: dict[str, list[dict[str, Any]]] = {}
    for name, modname in found:
        if args.names and name not in args.names:
            continue
        try:
            mod = importlib.import_module(modname)
        except Exception:  # a broken module must not hide the others
            print(f"## {name}: import failed\n{traceback.format_exc()}")
            status = 1
            continue
        if not callable(getattr(mod, "run", None)):
            if args.names:                # a script module, not a table provider
                print(f"## {name}: no run() -- a script, see its docstring\n")
            continue
        name = str(getattr(mod, "NAME", name))
        title = str(getattr(mod, "TITLE", ""))
        print(f"## {name}", flush=True)
        t0 = time.perf_counter()
        try:
            rows = run_module(mod, args.quick)
        except Exception:
            print(f"FAILED\n{traceback.format_exc()}")
            status = 1
            continue
        everything[name] = rows
        fmt = getattr(mod, "format_table", None)
        if callable(fmt):
            table = str(fmt(rows))
        else:
            lines = [generic_table(rows)]
            notes = getattr(mod, "notes", None)
            if callable(notes):
                lines.extend(notes(rows))
            table = "\n".join(lines)
        if title and not table.startswith(title):
            print(title)
        print(table)
        print(f"({time.perf_counter() - t0:.1f} s)\n", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(everything, indent=2, default=str))
    return status


if __name__ == "__main__":
    sys.exit(main())
