"""``rig tune``: search the LQ weights (rho1..rho3 of Eq. 2.5) and the force-loop / fuzzy
settings for the least absorbed power over a Monte Carlo set of plants and roads, with
rattlespace, tire-load, fault and bump-stop constraints (optuna, resumable journal).

    rig tune [--config F] [--trials N] [--plants N] [--spread S] [--roads R ...]
             [--duration S] [--cluster ADDR] [--out DIR] [--json]

Writes tuned.toml (for ``rig design --config``), pareto.png and tune.json into --out;
running the same command again resumes the search (docs/scale-out.md).
"""

from __future__ import annotations

import argparse

from controller.config import load_config
from controller.modes import BANK_MODES
from hil.sim.montecarlo import MAX_SPREAD
from rig import argtypes, strict_json
from rig.terminal import refuse

MAX_TRIALS = 100_000
MAX_PLANTS = 10_000
MAX_BATCH = 1024


def _bound(text: str) -> float | None:
    """A ratio to passive in (0, 100], or ``baseline`` (None)."""
    if text.strip().lower() == "baseline":
        return None
    return float(argtypes.real(0.0, 100.0, lo_open=True)(text))


_bound.__name__ = "bound"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=argtypes.integer(1, MAX_TRIALS), default=40,
                   help="trials in total (a resumed search runs the missing ones; "
                        "default 40)")
    p.add_argument("--plants", type=argtypes.integer(1, MAX_PLANTS), default=4,
                   help="Monte Carlo plants per trial (default 4)")
    p.add_argument("--spread", type=argtypes.real(0.0, MAX_SPREAD), default=0.05,
                   help=f"relative std of M, m, K, C, Kt, Ct (0..{MAX_SPREAD}, default 0.05)")
    p.add_argument("--roads", nargs="+", type=argtypes.road, default=["rough-course"],
                   metavar="ROAD", help="roads every plant runs (default rough-course)")
    p.add_argument("--speed", type=argtypes.config_real("noise.nominal_speed_mps", "m/s"),
                   default=11.176, help="m/s (default 25 mph)")
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_OFFLINE_S, "s",
                                                    lo_open=True),
                   default=10.0, help="s per run (default 10)")
    argtypes.add_controller_option(p, tuple(BANK_MODES), "fuzzy")
    p.add_argument("--seed", type=argtypes.seed, default=1,
                   help="plants, roads, sensors and the sampler (default 1)")
    p.add_argument("--rattlespace-bound", type=_bound, default=1.0, metavar="R",
                   help="largest mean rattlespace RMS / passive, or 'baseline' (weight "
                        "set 1's on the same runs; default 1 = passive)")
    p.add_argument("--tire-load-bound", type=_bound, default=1.0, metavar="R",
                   help="largest mean dynamic tire-load RMS / passive, or 'baseline' "
                        "(default 1 = passive)")
    p.add_argument("--batch", type=argtypes.integer(1, MAX_BATCH), default=1,
                   help="trials evaluated together (keeps a cluster busy; default 1)")
    argtypes.add_batch_options(p)
    p.add_argument("--out", default="tune", metavar="DIR", type=argtypes.output_dir,
                   help="tuned.toml, pareto.png, tune.json and the resumable journal "
                        "(default ./tune)")
    p.add_argument("--json", action="store_true",
                   help="print the result as strict JSON (null for a non-finite value)")
    p.add_argument("--no-progress", action="store_true")


def _line(name: str, r: dict[str, object]) -> str:
    w = r["weights"]
    assert isinstance(w, list)
    return (f"{name:<10} {r['absorbed_power_ratio']:>10.4f} {r['rattlespace_rms_ratio']:>10.4f} "
            f"{r['tire_load_rms_ratio']:>10.4f} {r['faults']:>6} {r['slams']:>6}  rho "
            + ", ".join(f"{x:.4g}" for x in w[:3]))


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    from hil.batch import make_executor
    from hil.tune import TunePlan, run_tune
    plan = TunePlan(trials=args.trials, plants=args.plants, spread=args.spread,
                    roads=tuple(args.roads), speed_mps=args.speed, duration_s=args.duration,
                    controller=args.controller, seed=args.seed,
                    rattlespace_bound=args.rattlespace_bound,
                    tire_load_bound=args.tire_load_bound, batch=args.batch)
    with make_executor(args.cluster, args.jobs) as ex:   # refusals: rig.cli.REFUSALS
        res = run_tune(cfg, plan, args.out, ex, progress=not args.no_progress)
    for f in res.failures:
        refuse("tune", f"{f}")
    if args.json:
        print(strict_json.dumps(res.as_json(), indent=1))
    else:
        print(f"{len(res.trials)} trials in {res.wall_s:.0f} s; bounds: rattlespace RMS "
              f"<= {res.bounds['rattlespace_rms_ratio']:.4f}, tire load RMS <= "
              f"{res.bounds['tire_load_rms_ratio']:.4f} x passive")
        print(f"{'':<10} {'power':>10} {'rattle':>10} {'tire':>10} {'faults':>6} {'slams':>6}"
              "  (ratios to passive, mean over the runs)")
        print(_line("baseline", res.baseline))
        if res.best is not None:
            print(_line(f"best #{res.best['number']}", res.best))
        else:
            print("no trial met the constraints")
        for path in res.files:
            print(f"wrote {path}")
    return 0 if res.best is not None else 1
