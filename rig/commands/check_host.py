"""``rig check-host [--seconds N] [--json]``: can this computer run the rig loop?

Paces a thread at the configured loop rate with the loop's own real-time set-up
(``--rt-priority``, ``--cpu``, ``--no-realtime`` as ``rig run``) and judges the wake-up
lateness against the configuration's budgets (:mod:`rig.rt.hostcheck`); ``cyclictest``
runs alongside when installed (:mod:`rig.rt.cyclictest`).  Exit status 0 when the host
holds the budgets, 1 when not (with what to change), 2 for a bad argument or config.
"""

from __future__ import annotations

import argparse
import math

from controller.config import load_config
from rig import argtypes, strict_json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=argtypes.real(0.0, 3600.0, "s", lo_open=True),
                   default=10.0, metavar="N", help="measure for N seconds (default 10)")
    argtypes.add_realtime_options(p, host_check=True)
    p.add_argument("--no-cyclictest", action="store_true",
                   help="do not run cyclictest alongside")
    p.add_argument("--json", action="store_true", help="print the result as strict JSON")


def _us(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{x * 1e6:.0f}"


def run(args: argparse.Namespace) -> int:
    from rig.rt import cyclictest
    from rig.rt.hostcheck import Latency, check_host

    cfg = load_config(args.config)
    cpus = tuple(args.cpu or ())
    rt = argtypes.realtime_request(args)
    ct: cyclictest.CyclictestRun | str | None = None
    if not args.no_cyclictest:
        ct = cyclictest.start(args.seconds, round(cfg.sample_time_s * 1e6),
                              0 if rt is None else rt.fifo_priority, cpus)
    result = check_host(cfg, args.seconds, rt)
    other: Latency | str | None = ct.finish() if isinstance(ct, cyclictest.CyclictestRun) \
        else ct
    if args.json:
        doc = result.as_dict()
        doc["cyclictest"] = (None if other is None else
                             {"error": other} if isinstance(other, str) else other.as_dict())
        print(strict_json.dumps(doc))
        return 0 if result.ok else 1
    lat, b = result.latency, result.budget
    print(f"rig check-host: {result.seconds:g} s at {1.0 / b.period_s:g} Hz, "
          f"kernel {result.kernel}")
    got = ", ".join(f"{k}={v}" for k, v in result.realtime.get("granted", {}).items())
    not_got = ", ".join(f"{k} ({v})" for k, v in result.realtime.get("denied", {}).items())
    print(f"real-time set-up: got {got or 'nothing'}; not got {not_got or 'nothing'}")
    head = f"{'lateness [us]':16} {'p50':>8} {'p99':>8} {'p99.99':>8} {'max':>8} {'samples':>8}"
    print(head)
    rows: list[tuple[str, Latency]] = [("rig loop pacing", lat)]
    if isinstance(other, Latency):
        rows.append(("cyclictest", other))
    for name, x in rows:
        print(f"{name:16} {_us(x.p50_s):>8} {_us(x.p99_s):>8} {_us(x.p9999_s):>8} "
              f"{_us(x.max_s):>8} {x.samples:>8}")
    if isinstance(other, str):
        print(other)
    print(f"budgets: staleness {_us(b.stale_s)} us (safety.stale_ticks {b.stale_ticks} x "
          f"{_us(b.period_s)} us), overrun threshold {_us(b.overrun_threshold_s)} us "
          f"(safety.overrun_threshold_s); {lat.skipped} deadlines skipped")
    print(result.verdict.line())
    for note in result.verdict.notes:
        print(f"note: {note}")
    for advice in result.verdict.advice:
        print(f"to change: {advice}")
    return 0 if result.ok else 1
