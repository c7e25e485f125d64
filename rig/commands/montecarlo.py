"""``rig montecarlo``: robustness runs with M, m, K, Kt, C, Ct drawn around nominal.

    rig montecarlo --runs 8 --spread 0.05 --road rough-course --controller fuzzy --out mc/
    rig montecarlo --runs 1000 --cluster tcp://scheduler:8786     (docs/scale-out.md)
"""

from __future__ import annotations

import argparse

from controller.config import load_config
from hil.batch import make_executor
from hil.sim.closed_loop import CONTROLLERS
from hil.sim.montecarlo import MAX_RIDE_HEIGHT_STD_M, MAX_SPREAD, RIDE_HEIGHT_STD_M, run_montecarlo
from hil.sim.roads import ROAD_NAMES, make_road
from rig import argtypes, strict_json
from rig.terminal import refuse

#: most Monte Carlo runs and worker processes of one command
MAX_RUNS = 10_000

SUMMARY_KEYS = ("absorbed_power", "accel_rms_mps2", "wk_rms_mps2", "rattlespace_rms_m",
                "rattlespace_peak_m", "tire_load_rms_ratio", "time_off_ground_fraction",
                "bump_stop_time_s", "force_rms_n", "n_faults", "unstable")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=argtypes.integer(1, MAX_RUNS), default=8,
                   help=f"number of runs (1..{MAX_RUNS}, default 8)")
    p.add_argument("--spread", type=argtypes.real(0.0, MAX_SPREAD), default=0.05,
                   help="relative standard deviation of every parameter "
                        f"(0..{MAX_SPREAD}, default 0.05)")
    p.add_argument("--road", default="rough-course", type=argtypes.road,
                   help=", ".join(ROAD_NAMES))
    p.add_argument("--speed", type=argtypes.config_real("noise.nominal_speed_mps", "m/s"),
                   default=11.176, help="m/s (default 25 mph)")
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_OFFLINE_S, "s",
                                                    lo_open=True),
                   default=10.0, help="s per run (default 10)")
    argtypes.add_observe_option(p)
    argtypes.add_controller_option(p, CONTROLLERS, "fuzzy")
    argtypes.add_weights_option(p, None)
    p.add_argument("--seed", type=argtypes.seed, default=1)
    argtypes.add_batch_options(p)
    p.add_argument("--out", default=None, metavar="DIR", type=argtypes.output_dir,
                   help="write montecarlo.png and montecarlo.json here (replaced)")
    p.add_argument("--ride-height-std", default=RIDE_HEIGHT_STD_M, metavar="M",
                   type=argtypes.real(0.0, MAX_RIDE_HEIGHT_STD_M, "m"),
                   help="std of the ride-height setting error [m]: each plant's static "
                        "position about the bump stops' centre, set by spring preload "
                        f"(default {RIDE_HEIGHT_STD_M:g}, at most {MAX_RIDE_HEIGHT_STD_M:g})")
    p.add_argument("--own-ride-height", action="store_true",
                   help="no preload adjustment: each plant sits at its own M g / K "
                        "(--ride-height-std is then not used)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as strict JSON (null for a non-finite value)")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    weights = cfg.design.weight_set if args.weights is None else args.weights
    try:
        road = make_road(args.road, args.speed, args.observe + args.duration,
                         cfg.sample_time_s, args.seed)
        with make_executor(args.cluster, args.jobs) as ex:
            res = run_montecarlo(cfg, road, args.runs, controller=args.controller,
                                 weight_set=weights, spread=args.spread, seed=args.seed,
                                 workers=args.jobs, progress=not args.no_progress,
                                 out_dir=args.out,
                                 ride_height_std_m=(None if args.own_ride_height
                                                    else args.ride_height_std),
                                 executor=ex, observe_s=args.observe)
    except ValueError as exc:       # a bad road or spread (others: rig.cli.REFUSALS)
        refuse("montecarlo", f"{exc}")
        return 2
    for f in res.failed_runs:
        refuse("montecarlo", f"{f['case']} failed: {f['error']}")
    if args.json:
        print(strict_json.dumps({"summary": res.summary, "unstable_runs": res.unstable_runs,
                                 "faulted_runs": res.faulted_runs,
                                 "failed_runs": res.failed_runs, "png": res.png}, indent=1))
    elif res.summary:
        print(f"{args.runs} runs, {args.controller} (weights {weights}), {road.name} at "
              f"{road.speed_mps:g} m/s, spread {args.spread:g}")
        print(f"{'metric':<26} {'mean':>11} {'std':>11} {'min':>11} {'max':>11}")
        for k in SUMMARY_KEYS:
            s = res.summary[k]
            print(f"{k:<26} " + " ".join(f"{s[x]:>11.4g}" for x in ("mean", "std", "min",
                                                                     "max")))
        print(f"unstable runs: {res.unstable_runs or 'none'}; "
              f"faulted runs: {res.faulted_runs or 'none'}")
        if res.png:
            print(f"figure: {res.png}")
    return 1 if res.unstable_runs or res.failed_runs else 0
