"""``rig hil``: run the emulated rig as a CAN node, in real time, as its own process.

Runs until ``--duration`` seconds have passed or SIGINT / SIGTERM arrives, then prints
one summary line (frames sent / received, bad frames, watchdog trips...).  Exit status 0
on a clean stop, 1 if the bus cannot be opened, 2 for bad arguments or configuration.
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from types import FrameType

import can

from controller.config import load_config
from hil.faults import FaultSchedule
from hil.node import DEFAULT_WATCHDOG_S, RigNode
from hil.sim.roads import make_road
from rig import argtypes
from rig.bus.core import open_bus
from rig.terminal import refuse

#: longest road generated; longer runs replay it cyclically
MAX_ROAD_S = 120.0
#: longest drive watchdog timeout (a minute without a command is no watchdog)
MAX_WATCHDOG_MS = 60_000.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--interface", choices=("socketcan", "virtual"), default=None,
                   help="CAN interface (default: can.interface of the config)")
    p.add_argument("--channel", default=None, help="e.g. vcan0 (default: can.channel)")
    p.add_argument("--road", default="rough-course", type=argtypes.road,
                   help="road name (iso-A..iso-H, rough-course, datp, bump, pothole, "
                        "sweep, flat, csv:PATH); default rough-course")
    p.add_argument("--excite", action="store_true",
                   help="identification run: hold the road (shaker) at rest, i.e. --road "
                        "flat, while the controller (`rig run --excite`) plays its "
                        "excitation (docs/identify.md)")
    p.add_argument("--speed", type=argtypes.config_real("noise.nominal_speed_mps", "m/s"),
                   default=None, metavar="V",
                   help="vehicle speed [m/s] (default: noise.nominal_speed_mps)")
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_SERVICE_S, "s",
                                                    lo_open=True),
                   default=None, metavar="S",
                   help="stop after S seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--faults", default=None, metavar="FILE", type=argtypes.input_file,
                   help="fault schedule (TOML or JSON, see hil/faults.py)")
    p.add_argument("--seed", type=argtypes.seed, default=None,
                   help="seed for road, sensor noise and random faults")
    p.add_argument("--watchdog-ms", type=argtypes.real(0.0, MAX_WATCHDOG_MS, "ms",
                                                       lo_open=True),
                   default=DEFAULT_WATCHDOG_S * 1e3,
                   help="drive watchdog timeout [ms] (default 5)")
    p.add_argument("--rt-priority", type=argtypes.rt_priority, default=0,
                   help="ask for SCHED_FIFO at this priority (1..99; 0 = no)")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    speed = cfg.noise.nominal_speed_mps if args.speed is None else args.speed
    road_s = MAX_ROAD_S if args.duration is None else min(args.duration, MAX_ROAD_S)
    seed = cfg.sensors.seed if args.seed is None else args.seed
    if args.excite:
        args.road = "flat"
    road = make_road(args.road, speed, road_s, cfg.sample_time_s, seed)
    faults = FaultSchedule.load(args.faults) if args.faults else FaultSchedule()
    if args.seed is not None:
        faults = FaultSchedule(faults.windows, seed=args.seed)
    overrides = {k: v for k, v in (("interface", args.interface), ("channel", args.channel))
                 if v is not None}
    try:
        bus = open_bus(cfg.can, role="rig", **overrides)
    except (can.CanError, OSError, ValueError) as exc:
        refuse("hil", f"cannot open the CAN bus: {exc}")
        return 1
    stop = threading.Event()

    def _stop(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        from rig.rt.realtime import RealtimeRequest, apply_realtime
        apply_realtime(RealtimeRequest(fifo_priority=args.rt_priority, lock_memory=False,
                                       timer_slack_ns=1, freeze_gc=False))
    except ImportError:  # pragma: no cover - optional
        pass
    try:
        node = RigNode(bus, cfg, road, faults, watchdog_timeout_s=args.watchdog_ms * 1e-3,
                       seed=seed, record_ticks=1, fd=cfg.can.fd)
        t0 = time.monotonic()
        stats = node.run(stop, realtime=True, duration_s=args.duration)
        wall = time.monotonic() - t0
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        bus.shutdown()
    print(f"rig hil: {wall:.2f} s on {bus.channel_info}: {stats.summary()}")
    return 0
