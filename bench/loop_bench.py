"""Loop benchmark: the 1 kHz service loop against the emulated rig, in-process.

    python -m bench.loop_bench [--seconds 60] [--json] [--no-realtime]

Cases (each ``--seconds`` long in all, run in interleaved rounds of at most 10 s so that
a drifting machine affects every case alike; each segment starts with 0.5 s of warm-up
that is not counted):

1. ``bare``: loop armed (ACTIVE, fuzzy bank + PI force loop), recording and telemetry off;
2. ``rec`` / ``tel``: the MCAP recording (writer process) or the Zenoh telemetry
   (loopback) on;
3. ``rec+tel``: both on.

Per case: wake-up lateness ("period jitter" of a loop on absolute deadlines) p50 / p99 /
p99.9 / max, step time (wake-up to end of tick, CAN I/O included) p50 / p99 / max,
deadline misses (> 500 us late), skipped deadlines, faults; then the ratio of the p99s.
Two micro-measurements explain the floor: python-can's virtual-bus cost of one tick's
frames (3 received + 1 sent) and the wake-up lateness of ``time.sleep`` with the default
50 us timer slack vs 1 ns.

The rig (RigNode) runs in its own thread, like ``rig demo``: both share the GIL, so the
numbers include that contention.  Timing goals live here, never in test asserts.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import socket
import sys
import tempfile
import threading
import time
import uuid
from typing import Any

import numpy as np

WARM_S = 0.5
SEGMENT_S = 10.0
#: case -> (recording, telemetry)
CASES = {"bare": (False, False), "rec": (True, False), "tel": (False, True),
         "rec+tel": (True, True)}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rig_and_service(cfg: Any, design_path: str, road_s: float, **options: Any
                     ) -> tuple[Any, Any, Any]:
    """The emulated rig (bus, node) and the service on a fresh virtual channel."""
    from hil.node import RigNode
    from hil.roads import make_road
    from rig.bus import open_bus
    from rig.service import Service, ServiceOptions

    channel = f"bench-{uuid.uuid4().hex}"
    rig_bus = open_bus(cfg.can, role=None, interface="virtual", channel=channel)
    road = make_road("rough-course", 11.176, road_s, cfg.sample_time_s, seed=1)
    node = RigNode(rig_bus, cfg, road, record_ticks=1000)
    svc = Service(cfg, ServiceOptions(design_path=design_path, interface="virtual",
                                      channel=channel, realtime=None,
                                      install_signal_handlers=False, **options))
    return rig_bus, node, svc


def run_case(cfg: Any, seconds: float, recording: bool, telemetry: bool, realtime: bool,
             design_path: str, switch_interval_s: float = 0.0001,
             cpus: tuple[int, ...] = ()) -> dict[str, Any]:
    from rig.protocol import LifecycleState
    from rig.realtime import RealtimeRequest, restore_gc

    rate = cfg.design.sample_rate_hz
    tmp = tempfile.TemporaryDirectory()
    rig_bus, node, svc = _rig_and_service(
        cfg, design_path, seconds + 5.0,
        record=os.path.join(tmp.name, "bench.mcap") if recording else None,
        recording=recording, telemetry=telemetry,
        timing_ring=round((seconds + 2 * WARM_S) * rate))
    warm = round(WARM_S * rate)
    end = warm + round(seconds * rate)
    state = {"rig": -1, "measured_from": -1}
    stop_rig = threading.Event()
    rig_threads: list[threading.Thread] = []
    period_ns = round(1e9 / rate)

    def run_rig(start_ns: int) -> None:
        """The emulated rig's thread: off the loop's CPU when the loop is pinned (the
        thread inherits the loop thread's affinity and policy), like other hardware."""
        if cpus:
            others = set(range(os.cpu_count() or 1)) - set(cpus)
            if others:
                os.sched_setaffinity(0, others)
        node.run(stop_rig, start_ns=start_ns)

    def on_tick(loop: Any) -> None:
        k = loop.tick_count
        if state["rig"] < 0:
            if k >= 100:
                state["rig"] = k
                # like rig demo: the rig ticks half a period after the loop's deadlines
                start = loop.t_ns - loop.lateness_ns + period_ns + period_ns // 2
                rig_threads.append(threading.Thread(target=run_rig, args=(start,),
                                                    daemon=True))
                rig_threads[0].start()
            return
        # like the demo's operator: after a fault (a host stall silences the rig now and
        # then), reset and re-arm as soon as the condition has cleared
        lc = loop.lifecycle
        if lc.state is LifecycleState.FAULT and loop.monitor.condition.name == "NONE":
            loop.request("reset", timeout_s=None)
        if lc.state is LifecycleState.INACTIVE and not loop.health_problem():
            loop.request("arm", timeout_s=None)
        if state["measured_from"] < 0 and k >= state["rig"] + warm:
            state["measured_from"] = k
            loop.timing.reset()
        elif state["measured_from"] >= 0 and k >= state["measured_from"] + end - warm:
            svc.stop_event.set()

    for _ in range(3):
        node.tick()
    while svc.bus.recv(0.0) is not None:
        pass
    report = (svc.apply_realtime(RealtimeRequest(switch_interval_s=switch_interval_s,
                                                 cpus=cpus))
              if realtime else None)
    faults: list[str] = []
    svc.loop.lifecycle.add_listener(
        lambda tr: faults.append(tr.fault_code.name) if tr.state is LifecycleState.FAULT
        else None)
    try:
        svc.run(on_tick=on_tick)
    finally:
        stop_rig.set()
        for th in rig_threads:
            th.join(5.0)
        rig_bus.shutdown()
        if report is not None:
            restore_gc()
    lat, step = svc.loop.timing.recent()
    out: dict[str, Any] = {
        "_lat_us": lat / 1000.0, "_step_us": step / 1000.0,
        "skipped": svc.loop.timing.skipped,
        "faults": faults,
        "rig_late_ticks": node.stats.late_ticks,
        "rig_max_lateness_us": node.stats.max_lateness_s * 1e6,
        "rig_resyncs": node.stats.resyncs,
        "dropped_recording": svc.recorder.dropped if svc.recorder else 0,
        "dropped_telemetry": svc.telemetry.dropped if svc.telemetry else 0,
        "realtime": report.as_dict() if report else None,
    }
    tmp.cleanup()
    return out


def _summarise(segments: list[dict[str, Any]]) -> dict[str, Any]:
    """Pool the samples of one case's segments; counts add up, maxima are maxima."""
    lat_us = np.concatenate([s["_lat_us"] for s in segments])
    step_us = np.concatenate([s["_step_us"] for s in segments])
    return {
        "ticks": int(lat_us.size),
        "lateness_p50_us": float(np.percentile(lat_us, 50)),
        "lateness_p99_us": float(np.percentile(lat_us, 99)),
        "lateness_p99_9_us": float(np.percentile(lat_us, 99.9)),
        "lateness_max_us": float(lat_us.max()),
        "step_p50_us": float(np.percentile(step_us, 50)),
        "step_p99_us": float(np.percentile(step_us, 99)),
        "step_max_us": float(step_us.max()),
        "misses_500us": int(np.sum(lat_us > 500.0)),
        "skipped": sum(s["skipped"] for s in segments),
        "faults": [f for s in segments for f in s["faults"]],
        "rig_late_ticks": sum(s["rig_late_ticks"] for s in segments),
        "rig_max_lateness_us": max(s["rig_max_lateness_us"] for s in segments),
        "rig_resyncs": sum(s["rig_resyncs"] for s in segments),
        "dropped_recording": sum(s["dropped_recording"] for s in segments),
        "dropped_telemetry": sum(s["dropped_telemetry"] for s in segments),
        "segment_step_p99_us": [float(np.percentile(s["_step_us"], 99)) for s in segments],
        "realtime": segments[0]["realtime"],
    }


def tick_hot_and_cold(cfg: Any, design_path: str, n: int = 4000) -> dict[str, float]:
    """``ControlLoop.tick`` (armed, virtual bus, one rig tick before each) timed back to
    back ("hot") and 0.8 ms apart ("cold": what the loop sees after its sleep), in one
    thread: the floor of the step time and what cold caches add to it."""
    rig_bus, node, svc = _rig_and_service(cfg, design_path, 2 * n / 1000 + 5,
                                          recording=False, telemetry=False)
    loop = svc.loop
    t = time.monotonic_ns()
    for _ in range(200):
        node.tick()
        loop.tick(t)
        t += 1_000_000
    loop.request("arm", timeout_s=None)
    out: dict[str, float] = {}
    for mode, gap_s in (("hot", 0.0), ("cold", 0.0008)):
        dt = np.zeros(n)
        for k in range(n):
            node.tick()
            if gap_s:
                time.sleep(gap_s)
            t0 = time.perf_counter_ns()
            loop.tick(t0)
            dt[k] = time.perf_counter_ns() - t0
        out[f"{mode}_p50_us"] = float(np.percentile(dt, 50) / 1e3)
        out[f"{mode}_p99_us"] = float(np.percentile(dt, 99) / 1e3)
    out["state"] = float(loop.lifecycle.state)
    svc.close()
    rig_bus.shutdown()
    return out


def virtual_bus_cost(n: int = 5000) -> dict[str, float]:
    """us per tick for python-can's virtual bus: 3 frames received + 1 sent."""
    import can

    from rig.bus import make_tx_message

    ch = f"cost-{uuid.uuid4().hex}"
    a = can.Bus(interface="virtual", channel=ch)
    b = can.Bus(interface="virtual", channel=ch)
    rx_msgs = [make_tx_message(0x100), make_tx_message(0x100), make_tx_message(0x200)]
    tx = make_tx_message(0x080)
    t_recv = t_send = 0
    for _ in range(n):
        for m in rx_msgs:
            b.send(m)
        t0 = time.perf_counter_ns()
        while a.recv(0.0) is not None:
            pass
        t1 = time.perf_counter_ns()
        a.send(tx)
        t2 = time.perf_counter_ns()
        while b.recv(0.0) is not None:
            pass
        t_recv += t1 - t0
        t_send += t2 - t1
    a.shutdown()
    b.shutdown()
    return {"recv_3_us": t_recv / n / 1000, "send_1_us": t_send / n / 1000,
            "tick_us": (t_recv + t_send) / n / 1000}


def sleep_lateness(slack_ns: int, n: int = 2000) -> dict[str, float]:
    """Wake-up lateness of absolute-deadline 1 ms sleeps in a thread with ``slack_ns``."""
    result: dict[str, float] = {}

    def worker() -> None:
        if hasattr(os, "sched_setscheduler"):   # an ordinary thread: RT threads get no slack
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.prctl(29, ctypes.c_ulong(slack_ns), 0, 0, 0)   # PR_SET_TIMERSLACK
        except OSError:
            pass
        late = np.zeros(n)
        deadline = time.monotonic_ns() + 1_000_000
        for i in range(n):
            time.sleep(max(deadline - time.monotonic_ns(), 0) * 1e-9)
            late[i] = (time.monotonic_ns() - deadline) / 1000.0
            deadline += 1_000_000
        result.update({"p50_us": float(np.percentile(late, 50)),
                       "p99_us": float(np.percentile(late, 99)),
                       "over_100us_pct": float(100.0 * np.mean(late > 100.0))})

    th = threading.Thread(target=worker)
    th.start()
    th.join()
    return result


def measure(seconds: float, case_names: list[str], *, realtime: bool = True,
            switch_interval_s: float = 0.0001, cpu: int | None = None) -> dict[str, Any]:
    """Run the cases one after another in this process; the result of ``--json``."""
    from controller.artifact import save_design
    from controller.config import default_config
    from hil.sim import cached_design

    # telemetry on a free loopback port (the design is for this configuration)
    cfg = default_config().replace(
        telemetry={"endpoints": [f"tcp/127.0.0.1:{_free_port()}"]})
    with tempfile.TemporaryDirectory() as tmp:
        design_path = os.path.join(tmp, "design.npz")
        save_design(cached_design(cfg), design_path)
        cpus = () if cpu is None else (cpu,)
        # the machine drifts (other load, the host): the cases take turns in segments
        # of at most SEGMENT_S, and each case's samples are pooled
        rounds = max(1, math.ceil(seconds / SEGMENT_S))
        segments: dict[str, list[dict[str, Any]]] = {name: [] for name in case_names}
        for _ in range(rounds):
            for name in case_names:
                segments[name].append(run_case(
                    cfg, seconds / rounds, CASES[name][0], CASES[name][1], realtime,
                    design_path, switch_interval_s, cpus=cpus))
        cases = {name: _summarise(segs) for name, segs in segments.items()}
        tick = tick_hot_and_cold(cfg, design_path)
    micro = {"virtual_bus": virtual_bus_cost(), "tick": tick,
             "sleep_slack_50us": sleep_lateness(50_000),
             "sleep_slack_1ns": sleep_lateness(1)}
    bare, full = cases["bare"], cases["rec+tel"]
    seg_ratios = [f / b for f, b in zip(full["segment_step_p99_us"],
                                         bare["segment_step_p99_us"], strict=True)]
    return {"seconds": seconds, "rounds": rounds, "cases": cases, "micro": micro,
            "p99_step_ratio_median_of_rounds": float(np.median(seg_ratios)),
            "p99_lateness_ratio": (full["lateness_p99_us"] / bare["lateness_p99_us"]
                                   if bare["lateness_p99_us"] > 0 else math.nan),
            "p99_step_ratio": full["step_p99_us"] / bare["step_p99_us"],
            "cpus": os.cpu_count(), "load": os.getloadavg(), "pinned_cpu": cpu}


_ROWS = [("lateness p50 [us]", "lateness_p50_us"), ("lateness p99 [us]", "lateness_p99_us"),
         ("lateness p99.9 [us]", "lateness_p99_9_us"), ("lateness max [us]",
                                                          "lateness_max_us"),
         ("step p50 [us]", "step_p50_us"), ("step p99 [us]", "step_p99_us"),
         ("step max [us]", "step_max_us"), ("misses > 500 us", "misses_500us"),
         ("skipped deadlines", "skipped"), ("ticks", "ticks"),
         ("rig thread max late [us]", "rig_max_lateness_us")]


def format_report(res: dict[str, Any]) -> str:
    cases = res["cases"]
    out = [f"loop benchmark: 1 kHz, {res['seconds']:g} s per case in {res['rounds']} "
           f"interleaved rounds, emulated rig in-process "
           f"(half a period after the loop), load {res['load'][0]:.1f} on {res['cpus']} CPUs"
           + (f", loop pinned to CPU {res['pinned_cpu']}" if res["pinned_cpu"] is not None
              else "")]
    out.append(f"{'':26}" + "".join(f" {name:>10}" for name in cases))
    for label, key in _ROWS:
        out.append(f"{label:26}" + "".join(f" {c[key]:>10.1f}" for c in cases.values()))
    out.append(f"{'faults':26}" + "".join(f" {','.join(c['faults']) or '-':>10}"
                                          for c in cases.values()))
    bare, full = cases["bare"], cases["rec+tel"]
    out.append(f"rec+tel vs bare: lateness p99 {full['lateness_p99_us']:.1f} vs "
               f"{bare['lateness_p99_us']:.1f} us (x{res['p99_lateness_ratio']:.2f}), "
               f"step p99 {full['step_p99_us']:.1f} vs {bare['step_p99_us']:.1f} us "
               f"(x{res['p99_step_ratio']:.2f}; median of the {res['rounds']} rounds' "
               f"ratios x{res['p99_step_ratio_median_of_rounds']:.2f}); goal: at most x1.10")
    for name, c in cases.items():
        miss_pct = 100.0 * c["misses_500us"] / max(c["ticks"], 1)
        out.append(f"goals [{name}]: whole tick p99 {c['step_p99_us']:.0f} us "
                   f"({'met' if c['step_p99_us'] < 100 else 'NOT met'}, < 100 us); periods "
                   f"> 500 us late {miss_pct:.3f} % "
                   f"({'met' if miss_pct < 0.1 else 'NOT met'}, < 0.1 %)")
    tk = res["micro"]["tick"]
    out.append(f"one tick in a plain thread: back to back p50 {tk['hot_p50_us']:.1f} / p99 "
               f"{tk['hot_p99_us']:.1f} us; 0.8 ms apart (cold caches) p50 "
               f"{tk['cold_p50_us']:.1f} / p99 {tk['cold_p99_us']:.1f} us")
    vb = res["micro"]["virtual_bus"]
    out.append(f"virtual bus per tick: {vb['tick_us']:.1f} us (3 recv {vb['recv_3_us']:.1f}, "
               f"1 send {vb['send_1_us']:.1f})")
    for name in ("sleep_slack_50us", "sleep_slack_1ns"):
        m = res["micro"][name]
        out.append(f"{name:22} wake-up p50 {m['p50_us']:.0f} us, p99 {m['p99_us']:.0f} us, "
                   f"> 100 us late {m['over_100us_pct']:.1f} %")
    return "\n".join(out)


NAME = "loop"
TITLE = "the 1 kHz service loop against the emulated rig (bare, rec, tel, rec+tel)"


def run(quick: bool = False) -> list[dict[str, Any]]:
    """``python -m bench`` entry: one row per case (60 s each; 5 s with ``quick``)."""
    res = measure(5.0 if quick else 60.0, list(CASES))
    rows = [{"case": name, **{k: v for k, v in c.items() if not isinstance(v, dict | list)}}
            for name, c in res["cases"].items()]
    rows[0]["_report"] = format_report(res)
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    return str(rows[0].get("_report", ""))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-realtime", action="store_true")
    ap.add_argument("--switch-interval-us", type=float, default=100.0,
                    help="sys.setswitchinterval for the run (default 100 us)")
    ap.add_argument("--cpu", type=int, default=None,
                    help="pin the loop thread to this CPU (the emulated rig and the "
                         "recording writer go to the others), like CPUAffinity= in "
                         "deploy/rig.service")
    ap.add_argument("--cases", default="bare,rec,tel,rec+tel",
                    help=f"comma-separated, from {', '.join(CASES)} (bare and rec+tel "
                         "are needed for the ratio)")
    args = ap.parse_args(argv)
    names = args.cases.split(",")
    unknown = set(names) - set(CASES)
    if unknown or not {"bare", "rec+tel"} <= set(names):
        ap.error(f"--cases: unknown {sorted(unknown)}; bare and rec+tel are required")
    res = measure(args.seconds, names, realtime=not args.no_realtime,
                  switch_interval_s=args.switch_interval_us * 1e-6, cpu=args.cpu)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(format_report(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
