"""``rig demo``: the controller service against the emulated rig, in real time.

The emulated rig (:class:`hil.node.RigNode`, its own thread) and the service
(:class:`rig.service.Service`, the main thread) share python-can's in-process virtual
bus.  The first half of the run is passive (INACTIVE: Enable=0, the rig's bypass open);
at half time the demo arms the service (ACTIVE, fuzzy LQG bank).  A live line shows
time, lifecycle, rattlespace, absorbed power so far and overruns; at the end a table
compares the two halves (from the rig's true plant signals) with the loop timing of
each, and ``--json`` prints the same as JSON.  The run is recorded (MCAP).

If the service latches a fault the demo, acting as the operator, resets and re-arms
(at most ``--max-rearms`` times); every fault is listed in the summary.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from controller.config import RigConfig, load_config
from rig import argtypes, strict_json

SETTLE_S = 0.5     # skipped at the start of each half (start-up / switching transients)
WARM_TICKS = 200   # loop ticks before the emulated rig starts
MAX_REARMS = 1000


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_OFFLINE_S, "s",
                                                    lo_open=True),
                   default=20.0, metavar="S",
                   help="total run time; passive first half, active second (default 20)")
    p.add_argument("--record", metavar="PATH", default=None, type=argtypes.recording_target,
                   help="new MCAP file or a directory (default: recording.directory); "
                        "a recording is never overwritten")
    p.add_argument("--no-record", action="store_true", help="do not record")
    p.add_argument("--json", action="store_true",
                   help="print the summary as strict JSON (stdout; null for a non-finite "
                        "value)")
    p.add_argument("--road", default="rough-course", type=argtypes.road,
                   help="road (see `rig sim --help`)")
    p.add_argument("--speed", type=argtypes.config_real("noise.nominal_speed_mps", "m/s"),
                   default=11.176, metavar="MPS",
                   help="vehicle speed [m/s] (default 11.176 = 25 mph)")
    p.add_argument("--blending", default="fuzzy",
                   choices=("fuzzy", "bayes", "moving", "single"))
    p.add_argument("--weight-set", type=argtypes.weight_set, default=None, metavar="N",
                   help="weight set, 1-based into design.weight_sets "
                        "(default: design.weight_set)")
    p.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    p.add_argument("--no-realtime", action="store_true", help="skip the real-time set-up")
    p.add_argument("--max-rearms", type=argtypes.integer(0, MAX_REARMS), default=10,
                   metavar="N",
                   help="reset + re-arm after a fault at most N times (default 10)")
    p.add_argument("--seed", type=argtypes.seed, default=None,
                   help="road seed (default sensors.seed)")
    p.add_argument("-q", "--quiet", action="store_true", help="no live progress line")


# ---------------------------------------------------------------------------- the rig side


def _make_traced_node(bus: Any, cfg: RigConfig, road: Any, n_ticks: int) -> Any:
    """A RigNode that also keeps the true plant signals of every tick (for the metrics)."""
    from hil.node import RigNode

    class TracedNode(RigNode):
        def __init__(self) -> None:
            super().__init__(bus, cfg, road, record_ticks=min(n_ticks, 600_000))
            self.n = n_ticks
            self.trace = {k: np.zeros(n_ticks) for k in (
                "accel_mps2", "rattlespace_m", "tire_force_n", "force_n",
                "hydraulic_power_w", "off_ground_s", "bump_stop_s", "bypass_open")}
            self.count = 0

        def tick(self) -> None:
            super().tick()
            i = self.count
            if i < self.n:
                p = self.plant
                rs, force, acc = p.true_signals()
                tr = self.trace
                tr["accel_mps2"][i] = acc
                tr["rattlespace_m"][i] = rs
                tr["force_n"][i] = force
                tr["tire_force_n"][i] = p.tire_force_n
                tr["hydraulic_power_w"][i] = p.hydraulic_power_w
                tr["off_ground_s"][i] = p.off_ground_time_last_tick_s
                tr["bump_stop_s"][i] = p.bump_stop_time_last_tick_s
                tr["bypass_open"][i] = self.bypass_applied
                self.count = i + 1

    return TracedNode()


# ---------------------------------------------------------------------------- progress


class _Progress:
    """The live line (own thread): absorbed power from the rig's true acceleration,
    filtered incrementally by F(s) per phase."""

    def __init__(self, cfg: RigConfig, node: Any, service: Any, arm_tick: int,
                 enabled: bool) -> None:
        from scipy import signal

        self.node = node
        self.service = service
        self.arm_tick = arm_tick
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        dt = cfg.sample_time_s
        z, p, k = signal.tf2zpk(cfg.design.human_filter_num, cfg.design.human_filter_den)
        self.sos = signal.zpk2sos(*signal.bilinear_zpk(z, p, k, fs=1.0 / dt))
        self.zi = np.zeros((self.sos.shape[0], 2))
        self.done = 0
        self.sum_sq = [0.0, 0.0]
        self.n = [0, 0]
        self.dt = dt
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="demo-progress", daemon=True)
        self._last_plain = 0.0

    def start(self) -> None:
        if self.enabled:
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
            self.update(final=True)

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            self.update()

    def update(self, final: bool = False) -> None:
        from scipy import signal

        end = self.node.count
        if end > self.done:
            acc = self.node.trace["accel_mps2"][self.done:end]
            y, self.zi = signal.sosfilt(self.sos, acc, zi=self.zi)
            idx = np.arange(self.done, end)
            active = idx >= self.arm_tick
            self.sum_sq[0] += float(np.sum(np.square(y[~active])))
            self.sum_sq[1] += float(np.sum(np.square(y[active])))
            self.n[0] += int(np.sum(~active))
            self.n[1] += int(np.sum(active))
            self.done = end
        loop = self.service.loop
        p = [self.sum_sq[i] / self.n[i] if self.n[i] else math.nan for i in (0, 1)]
        line = (f"t {end * self.dt:6.2f} s  {loop.lifecycle.state.name:<8}  "
                f"rattlespace {1e3 * loop.rattlespace_m:+7.2f} mm  "
                f"absorbed power passive {p[0]:.4f} active {p[1]:.4f}  "
                f"overruns {loop.timing.overruns}")
        if self.tty:
            sys.stderr.write("\r" + line + ("\n" if final else ""))
            sys.stderr.flush()
        elif final or time.monotonic() - self._last_plain >= 2.0:
            self._last_plain = time.monotonic()
            sys.stderr.write(line + "\n")
            sys.stderr.flush()


# ---------------------------------------------------------------------------- summary


def _half_metrics(cfg: RigConfig, node: Any, t0: int, t1: int,
                  lateness_ns: np.ndarray, step_ns: np.ndarray) -> dict[str, float]:
    from hil.metrics import compute_metrics

    tr = {k: v[t0:t1] for k, v in node.trace.items()}
    v = cfg.vehicle
    static_load = (v.sprung_mass_kg + v.unsprung_mass_kg) * v.gravity_mps2
    if t1 - t0 < 2:
        return {"ticks": float(max(t1 - t0, 0))}
    m = compute_metrics(cfg.sample_time_s, tr["accel_mps2"], tr["rattlespace_m"],
                        tr["tire_force_n"], static_load, tr["force_n"],
                        tr["hydraulic_power_w"], tr["off_ground_s"], tr["bump_stop_s"],
                        settle_s=SETTLE_S,
                        human_filter=(cfg.design.human_filter_num, cfg.design.human_filter_den))
    i0 = min(round(SETTLE_S / cfg.sample_time_s), t1 - t0 - 1)
    late = lateness_ns[t0 + i0:t1] / 1000.0
    step = step_ns[t0 + i0:t1] / 1000.0
    out = {
        "ticks": float(t1 - t0),
        "absorbed_power": m["absorbed_power"],
        "rattlespace_rms_m": m["rattlespace_rms_m"],
        "rattlespace_peak_m": m["rattlespace_peak_m"],
        "tire_load_rms_ratio": m["tire_load_rms_ratio"],
        "force_rms_n": m["force_rms_n"],
        "accel_rms_mps2": m["accel_rms_mps2"],
        "bypass_open_fraction": float(np.mean(tr["bypass_open"][i0:])),
    }
    if late.size:
        out.update({
            "lateness_p50_us": float(np.percentile(late, 50)),
            "lateness_p99_us": float(np.percentile(late, 99)),
            "lateness_max_us": float(np.max(late)),
            "step_p50_us": float(np.percentile(step, 50)),
            "step_p99_us": float(np.percentile(step, 99)),
            "step_max_us": float(np.max(step)),
            "overruns": float(np.sum(late > cfg.safety.overrun_threshold_s * 1e6)),
        })
    return out


_ROWS = (
    ("absorbed power [(m/s2)^2]", "absorbed_power", 1.0, "{:.4f}"),
    ("rattlespace RMS [mm]", "rattlespace_rms_m", 1e3, "{:.2f}"),
    ("tire load RMS / static", "tire_load_rms_ratio", 1.0, "{:.4f}"),
    ("actuator force RMS [N]", "force_rms_n", 1.0, "{:.0f}"),
    ("valve bypass open [%]", "bypass_open_fraction", 100.0, "{:.0f}"),
    ("loop lateness p50 [us]", "lateness_p50_us", 1.0, "{:.0f}"),
    ("loop lateness p99 [us]", "lateness_p99_us", 1.0, "{:.0f}"),
    ("loop lateness max [us]", "lateness_max_us", 1.0, "{:.0f}"),
    ("step time p99 [us]", "step_p99_us", 1.0, "{:.0f}"),
    ("overruns", "overruns", 1.0, "{:.0f}"),
)


def _table(passive: dict[str, float], active: dict[str, float]) -> str:
    lines = [f"{'':28} {'passive':>10} {'active':>10} {'active/passive':>15}"]
    for label, key, scale, fmt in _ROWS:
        a, b = passive.get(key, math.nan), active.get(key, math.nan)
        ratio = b / a if key in ("absorbed_power", "rattlespace_rms_m", "tire_load_rms_ratio") \
            and a else math.nan
        lines.append(f"{label:28} {fmt.format(a * scale):>10} {fmt.format(b * scale):>10} "
                     f"{'' if math.isnan(ratio) else f'{ratio:.3f}':>15}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    from hil.roads import RoadError, make_road
    from rig.bus import open_bus
    from rig.protocol import LifecycleState
    from rig.realtime import RealtimeRequest, restore_gc
    from rig.service import Service, ServiceOptions

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    cfg = load_config(args.config)
    rate = cfg.design.sample_rate_hz
    n_ticks = round(args.duration * rate)
    arm_tick = n_ticks // 2
    seed = cfg.sensors.seed if args.seed is None else args.seed
    try:
        road = make_road(args.road, args.speed, args.duration + 1.0, cfg.sample_time_s,
                         seed=seed)
    except RoadError as exc:
        print(f"rig demo: {exc}", file=sys.stderr)
        return 2
    channel = f"rig-demo-{os.getpid()}"
    rig_bus = open_bus(cfg.can, role=None, interface="virtual", channel=channel)
    node = _make_traced_node(rig_bus, cfg, road, n_ticks + 2000)
    if not args.quiet:
        print("rig demo: designing the bank ...", file=sys.stderr)
    service = Service(cfg, ServiceOptions(
        interface="virtual", channel=channel, duration_s=None, record=args.record,
        recording=False if args.no_record else None,
        telemetry=False if args.no_telemetry else None, blending=args.blending,
        weight_set=args.weight_set, realtime=None, install_signal_handlers=True,
        timing_ring=2 * n_ticks + 10_000),
        metadata={"source": "rig demo", "road": args.road, "speed_mps": args.speed,
                  "arm_tick": arm_tick})
    faults: list[dict[str, Any]] = []
    state = {"rearms": 0, "armed_at": -1, "rig_started_at": -1}
    stop_rig = threading.Event()
    rig_threads: list[threading.Thread] = []
    period_ns = service.loop.period_ns

    def on_tick(loop: Any) -> None:
        """Operator of the demo, in the loop thread (cheap except on events)."""
        if state["rig_started_at"] < 0:
            # the rig starts once the loop runs steadily (its drive watchdog arms with the
            # first command and trips after 5 ms without one); the thread inherits the
            # loop thread's real-time settings
            if loop.tick_count >= WARM_TICKS:
                state["rig_started_at"] = loop.tick_count
                # the rig ticks half a period after the loop: in one process the two
                # threads take turns with the GIL instead of waking together
                deadline = loop.t_ns - loop.lateness_ns
                rig_threads.append(threading.Thread(
                    target=node.run, args=(stop_rig,), name="emulated-rig", daemon=True,
                    kwargs={"start_ns": deadline + period_ns + period_ns // 2}))
                rig_threads[0].start()
            return
        k = node.count
        if k >= n_ticks:
            service.stop_event.set()
            return
        if k < arm_tick:
            return
        lc = loop.lifecycle
        if lc.state is LifecycleState.FAULT and state["rearms"] < args.max_rearms \
                and loop.monitor.condition.name == "NONE" \
                and loop.request("reset", timeout_s=None).accepted:
            state["rearms"] += 1
        if lc.state is LifecycleState.INACTIVE and not loop.health_problem() \
                and (state["armed_at"] < 0 or state["rearms"] > 0) \
                and loop.request("arm", timeout_s=None).accepted and state["armed_at"] < 0:
            state["armed_at"] = k

    def on_transition(tr: Any) -> None:
        if tr.state is LifecycleState.FAULT:
            t_rig = max(node.count, 0) / rate
            faults.append({"tick": tr.tick, "time_s": t_rig, "code": tr.fault_code.name,
                           "detail": tr.fault_detail, "reason": tr.reason})

    service.loop.lifecycle.add_listener(on_transition)
    report = None if args.no_realtime else service.apply_realtime(RealtimeRequest())
    # first rig ticks outside real time (numba / first-call costs): no command has armed the
    # rig's drive watchdog yet, so a slow first tick cannot trip it
    for _ in range(3):
        node.tick()
    while service.bus.recv(0.0) is not None:    # the controller has not seen these frames
        pass
    progress = _Progress(cfg, node, service, arm_tick, enabled=not args.quiet)
    progress.start()
    try:
        service.run(on_tick=on_tick)
    finally:
        progress.stop()
        stop_rig.set()
        for th in rig_threads:
            th.join(5.0)
        rig_bus.shutdown()
        if report is not None:
            restore_gc()

    loop = service.loop
    late, step = loop.timing.recent()
    # loop tick of rig tick k ~ k + offset (the rig started at loop tick `offset`)
    offset = max(state["rig_started_at"], 0) - (loop.timing.count - late.shape[0])
    late, step = late[max(offset, 0):], step[max(offset, 0):]
    n_done = min(node.count, late.shape[0])
    armed_at = state["armed_at"] if state["armed_at"] >= 0 else n_done
    passive = _half_metrics(cfg, node, 0, min(arm_tick, n_done), late, step)
    active = _half_metrics(cfg, node, min(armed_at, n_done), n_done, late, step)
    summary: dict[str, Any] = {
        "duration_s": args.duration, "road": args.road, "speed_mps": args.speed,
        "blending": args.blending, "weight_set": loop.weight_set,
        "armed_at_s": armed_at / rate if state["armed_at"] >= 0 else None,
        "passive": passive, "active": active,
        "ratios": {k: (active[k] / passive[k] if passive.get(k) else None)
                   for k in ("absorbed_power", "rattlespace_rms_m", "tire_load_rms_ratio")
                   if k in active and k in passive},
        "faults": faults, "rearms": state["rearms"],
        "final_state": loop.lifecycle.state.name,
        "timing": loop.timing.summary(),
        "recording": str(service.recording_path) if service.recording_path else None,
        "recording_dropped": service.recorder.dropped if service.recorder else 0,
        "recording_error": service.recorder.error if service.recorder else None,
        "rig": node.stats.as_dict(),
        "realtime": service.realtime_report.as_dict(),
        "exit_reason": service.exit_reason,
    }
    out = sys.stderr if args.json else sys.stdout
    print(f"\nrig demo: {args.road} at {args.speed} m/s, {args.duration:g} s "
          f"(passive, then {args.blending} bank armed at "
          f"{summary['armed_at_s'] if summary['armed_at_s'] is not None else '-'} s)", file=out)
    print(_table(passive, active), file=out)
    for f in faults:
        print(f"fault at {f['time_s']:.3f} s: {f['code']} ({f['reason']})", file=out)
    if active.get("bypass_open_fraction", 1.0) > 0.5:
        print(f"note: the controller was engaged for only "
              f"{100 * (1 - active.get('bypass_open_fraction', 1.0)):.0f} % of the second "
              f"half (faults above); load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} CPUs", file=out)
    if summary["recording"]:
        print(f"recording: {summary['recording']}", file=out)
    if args.json:
        print(strict_json.dumps(summary))
    return 0
