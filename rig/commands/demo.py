"""``rig demo``: the controller service against the emulated rig, in real time or in
lockstep.

The service (:class:`rig.service.runner.Service`, its loop in the main thread) and the emulated
rig (:class:`hil.node.RigNode` in a process of its own) talk CAN over a socket pair, as
``rig run`` and ``rig hil`` do over vcan on the bench; :class:`hil.harness.RigHarness`
sets them up (the same harness as the loop benchmark and the tests).  The summary's
plant figures are the rig's true signals, traced by the rig process in shared memory.
The first half of the run is passive (INACTIVE: Enable=0, the rig's bypass open);
at half time the demo arms the service (ACTIVE, fuzzy LQG bank).  A live line shows
time, lifecycle, rattlespace, absorbed power so far and overruns; at the end a table
compares the two halves (from the rig's true plant signals) with the loop timing of
each, and ``--json`` prints the same as JSON.  The run is recorded (MCAP).

``--timing`` (default ``auto``, resolved by :func:`rig.rt.timing_mode.choose_timing`):
``realtime`` runs both processes on their own 1 kHz deadlines (as ``rig run`` and ``rig
hil``; an ordinary host's stalls of a few ms show as SENSOR_STALE / drive watchdog);
``lockstep`` lets them take turns tick by tick (:mod:`rig.rt.lockstep`): the same frames
on the same wire, every safety check unchanged in ticks, the wall clock only pacing the
run (at most ``--max-speedup`` x real time) -- the same run, bit for bit, as
:func:`hil.stepped_run.record_emulated_run`.  The first line printed says which timing
runs and why.

If the service latches a fault the demo, acting as the operator, resets and re-arms
(at most ``--max-rearms`` times); every fault is listed in the summary.

SIGTERM / SIGINT at any point end the demo with exit status 0 and a message: during the
run it stops early (summary of what ran, recording complete); before the loop started
nothing is recorded.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from controller.config import RigConfig, load_config
from controller.modes import BANK_MODES
from rig import argtypes, strict_json
from rig.output_paths import OUTPUT_FAILED
from rig.rt.hostcheck import check_host
from rig.rt.timing_mode import AUTO_CHECK_S, TIMINGS, checked_in_own_thread, choose_timing

SETTLE_S = 0.5     # skipped at the start of each half (start-up / switching transients)
WARM_TICKS = 200   # loop ticks before the emulated rig starts
MAX_REARMS = 1000
EXCITE_TAIL_S = 0.5  # passive rest kept after an excitation (--excite)


def fault_line(fault: dict[str, Any]) -> str:
    """The summary's line of one fault: code, reason, and for SENSOR_STALE /
    OVERRUN_STREAK whether the host's lateness explains it (rig/service/host_lateness.py;
    the reason already carries the "(host lateness: ...)" phrase when it does)."""
    line = f"fault at {fault['time_s']:.3f} s: {fault['code']} ({fault['reason']})"
    hl = fault.get("host_lateness")
    if hl and not hl["attributed"] and fault["code"] in ("SENSOR_STALE", "OVERRUN_STREAK"):
        rig = (f", emulated rig at most {hl['rig_late_ms']:.1f} ms late"
               if hl["rig_checked"] else "")
        line += (f" (not host lateness: loop at most {hl['loop_late_ms']:.1f} ms late"
                 f"{rig} over {hl['window_ticks']} ticks, budget {hl['budget_ms']:g} ms)")
    return line


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
    argtypes.add_controller_option(p, tuple(BANK_MODES), "fuzzy")
    argtypes.add_weights_option(p, None)
    p.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    argtypes.add_foxglove_option(p)
    p.add_argument("--no-realtime", action="store_true",
                   help="skip the real-time set-up (lockstep never does it)")
    p.add_argument("--timing", choices=("auto", *TIMINGS), default="auto",
                   help="realtime: both processes on their own 1 kHz deadlines; lockstep: "
                        "in turns tick by tick, paced by the wall clock best effort (the "
                        "host's stalls cannot fault it); auto (default): lockstep for now")
    p.add_argument("--max-speedup", type=argtypes.real(0.0, 1e6, "x"), default=1.0,
                   metavar="F",
                   help="lockstep: run at most F x real time (default 1; 0 = as fast as "
                        "the two processes go)")
    p.add_argument("--max-rearms", type=argtypes.integer(0, MAX_REARMS), default=10,
                   metavar="N",
                   help="reset + re-arm after a fault at most N times (default 10)")
    p.add_argument("--seed", type=argtypes.seed, default=None,
                   help="road seed (default sensors.seed)")
    p.add_argument("--rig-watchdog-ms", type=argtypes.real(0.0, 1e7, "ms", lo_open=True),
                   default=None, metavar="MS",
                   help="the emulated drive's command watchdog (default 5, as `rig hil`)")
    p.add_argument("--excite", action="store_true",
                   help="identification run (docs/identify.md): the road held at rest "
                        "('flat'), armed excitation.duration_s + 0.5 s before the end, the "
                        "force reference is the excitation of [excitation] instead of the "
                        "bank's output; then `rig identify` the recording")
    p.add_argument("-q", "--quiet", action="store_true", help="no live progress line")


# ---------------------------------------------------------------------------- progress


class _Progress:
    """The live line (own thread): absorbed power from the rig's true acceleration,
    filtered incrementally by F(s) per phase."""

    def __init__(self, cfg: RigConfig, trace: Any, service: Any, arm_tick: int,
                 enabled: bool) -> None:
        from scipy import signal

        self.trace = trace
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

        end = self.trace.count
        if end > self.done:
            acc = self.trace.arrays["accel_mps2"][self.done:end]
            y, self.zi = signal.sosfilt(self.sos, acc, zi=self.zi)
            idx = np.arange(self.done, end)
            active = idx >= self.arm_tick
            self.sum_sq[0] += float(np.sum(np.square(y[~active])))
            self.sum_sq[1] += float(np.sum(np.square(y[active])))
            self.n[0] += int(np.sum(~active))
            self.n[1] += int(np.sum(active))
            self.done = end
        loop = self.service.loop
        p = [f"{self.sum_sq[i] / self.n[i]:.4f}" if self.n[i] else "-" for i in (0, 1)]
        line = (f"t {end * self.dt:6.2f} s  {loop.lifecycle.state.name:<8}  "
                f"rattlespace {1e3 * loop.rattlespace_m:+7.2f} mm  "
                f"absorbed power passive {p[0]} active {p[1]}  "
                f"overruns {loop.timing.overruns}")
        if self.tty:
            sys.stderr.write("\r" + line + ("\n" if final else ""))
            sys.stderr.flush()
        elif final or time.monotonic() - self._last_plain >= 2.0:
            self._last_plain = time.monotonic()
            sys.stderr.write(line + "\n")
            sys.stderr.flush()


# ---------------------------------------------------------------------------- summary


def _half_metrics(cfg: RigConfig, trace: Mapping[str, np.ndarray], t0: int, t1: int,
                  lateness_ns: np.ndarray, step_ns: np.ndarray) -> dict[str, float]:
    from controller.metrics import compute_metrics

    tr = {k: v[t0:t1] for k, v in trace.items()}
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


#: the compared figures (active / passive)
RATIO_KEYS = ("absorbed_power", "rattlespace_rms_m", "tire_load_rms_ratio")
#: a passive figure below this share of the active one is flat (the road at rest before
#: an excitation): no meaningful ratio
FLAT_SHARE = 1e-9


def ratio(passive: dict[str, float], active: dict[str, float], key: str
          ) -> tuple[float | None, str]:
    """active / passive of ``key`` and, when there is none, why (``"n/a ..."``)."""
    a, b = passive.get(key), active.get(key)
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
        return None, "n/a: too short"
    if abs(a) <= FLAT_SHARE * abs(b) or a == 0:
        return None, "n/a: passive flat"
    return b / a, ""


def _cell(d: dict[str, float], key: str, scale: float, fmt: str) -> str:
    v = d.get(key)
    return "n/a" if v is None or not math.isfinite(v) else fmt.format(v * scale)


def _table(passive: dict[str, float], active: dict[str, float]) -> str:
    lines = [f"{'':28} {'passive':>10} {'active':>10} {'active/passive':>17}"]
    for label, key, scale, fmt in _ROWS:
        r, why = ratio(passive, active, key) if key in RATIO_KEYS else (None, "")
        shown = why if r is None else f"{r:.3f}"
        lines.append(f"{label:28} {_cell(passive, key, scale, fmt):>10} "
                     f"{_cell(active, key, scale, fmt):>10} {shown:>17}")
    short = [f"{name} {int(d.get('ticks', 0))} ticks" for name, d in
             (("passive", passive), ("active", active)) if "absorbed_power" not in d]
    if short:
        lines.append(f"n/a: too short to measure ({', '.join(short)}; at least 2 each)")
    if any(ratio(passive, active, k)[1] == "n/a: passive flat" for k in RATIO_KEYS):
        lines.append("n/a: passive flat -- the passive part did not move (the road held at "
                     "rest before an excitation): no ratio to it")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    from hil.harness import RigHarness, RigProcessOptions
    from hil.node import DEFAULT_WATCHDOG_S
    from hil.sim.roads import make_road
    from rig.rt.realtime import RealtimeRequest
    from rig.rt.stop_signals import StopSignals
    from rig.service.runner import ServiceOptions
    from rig.wire.protocol import LifecycleState

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    stop: StopSignals = getattr(args, "stop_signals", None) or StopSignals()
    cfg = argtypes.with_foxglove(load_config(args.config), args.foxglove)
    rate = cfg.design.sample_rate_hz
    n_ticks = round(args.duration * rate)
    arm_tick = n_ticks // 2
    if args.excite:
        ex = cfg.excitation
        need = ex.rest_s + ex.duration_s + EXCITE_TAIL_S
        if args.duration < need:
            print(f"rig demo: --excite needs --duration >= {need:g} s (excitation.rest_s "
                  f"{ex.rest_s:g} + excitation.duration_s {ex.duration_s:g} + "
                  f"{EXCITE_TAIL_S:g} s of rest after it)", file=sys.stderr)
            return 2
        args.road = "flat"
        arm_tick = n_ticks - round((ex.duration_s + EXCITE_TAIL_S) * rate)
    # the rig process makes the road again; a bad one is refused here, before it starts
    make_road(args.road, args.speed, args.duration + 1.0, cfg.sample_time_s,
              seed=cfg.sensors.seed if args.seed is None else args.seed)
    timing, why = choose_timing(args.timing, lambda: checked_in_own_thread(
        lambda: check_host(cfg, AUTO_CHECK_S, None if args.no_realtime else RealtimeRequest())))
    lockstep = timing == "lockstep"
    pace = ""
    if lockstep:
        pace = ("; as fast as possible" if args.max_speedup <= 0
                else f"; at most {args.max_speedup:g} x real time")
    elif args.max_speedup != 1.0:
        pace = "; --max-speedup ignored: lockstep only"
    # the first line of a run (after the inputs are checked): which timing, and why
    print(f"rig demo: timing {timing} ({why}{pace})", file=sys.stderr, flush=True)
    watchdog_s = (DEFAULT_WATCHDOG_S if args.rig_watchdog_ms is None
                  else args.rig_watchdog_ms * 1e-3)
    # lockstep: no real-time set-up (a SCHED_FIFO process that waits for its turn gains
    # nothing and can starve the machine's other work)
    realtime = None if args.no_realtime or lockstep else RealtimeRequest()
    if not args.quiet:
        print("rig demo: designing the bank ...", file=sys.stderr)
    harness = RigHarness(
        cfg, ServiceOptions(
            duration_s=None, record=args.record,
            recording=False if args.no_record else None,
            telemetry=False if args.no_telemetry else None, controller=args.controller,
            weights=args.weights, realtime=realtime,
            timing_ring=2 * n_ticks + 10_000, excite=args.excite),
        RigProcessOptions(road=args.road, speed_mps=args.speed,
                          road_s=args.duration + 1.0, seed=args.seed,
                          watchdog_s=watchdog_s, trace_ticks=n_ticks + 2000,
                          realtime=realtime, lockstep=lockstep),
        metadata={"source": "rig demo", "road": args.road, "speed_mps": args.speed,
                  "arm_tick": arm_tick, "excitation": args.excite, "timing": timing},
        stop=stop, rig_start_ticks=WARM_TICKS, max_speedup=args.max_speedup)
    service, trace = harness.service, harness.trace
    if service.foxglove is not None and service.foxglove.state == "serving":
        print(f"rig demo: Foxglove view on {service.foxglove.url} (WebSocket "
              f"subprotocol {service.foxglove.subprotocol}; docs/foxglove.md)", file=sys.stderr)
    faults: list[dict[str, Any]] = []
    state = {"rearms": 0, "armed_at": -1}

    def on_tick(loop: Any) -> None:
        """Operator of the demo, in the loop thread (cheap except on events)."""
        if harness.result.rig_started_at < 0:
            return
        k = trace.count
        if k >= n_ticks:
            service.stop_event.set()
            return
        if k < arm_tick:
            return
        lc = loop.lifecycle
        if args.excite and state["armed_at"] >= 0:
            return      # an identification run is played once; a fault aborts it
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
            faults.append({"tick": tr.tick, "time_s": trace.count / rate,
                           "code": tr.fault_code.name, "detail": tr.fault_detail,
                           "reason": tr.reason, "host_lateness": tr.host_lateness})

    service.loop.lifecycle.add_listener(on_transition)
    progress = _Progress(cfg, trace, service, arm_tick, enabled=not args.quiet)
    progress.start()
    wall0 = time.monotonic()
    try:
        result = harness.run(on_tick=on_tick)
    finally:
        wall_s = time.monotonic() - wall0
        progress.stop()
        harness.close()
    if result.ticks_run == 0:
        print(f"rig demo: stopped by {service.stop_signal or 'request'} before the control "
              "loop started; nothing recorded", file=sys.stderr)
        return 0
    if result.rig_error:
        print(f"rig demo: emulated rig: {result.rig_error}", file=sys.stderr)

    loop = service.loop
    late, step = loop.timing.recent()
    # loop tick of rig tick k ~ k + offset (the rig started at loop tick `offset`)
    offset = max(result.rig_started_at, 0) - (loop.timing.count - late.shape[0])
    late, step = late[max(offset, 0):], step[max(offset, 0):]
    rig_trace = result.trace
    n_rig = len(rig_trace.get("accel_mps2", ()))
    n_done = min(n_rig, late.shape[0])
    armed_at = state["armed_at"] if state["armed_at"] >= 0 else n_done
    passive = _half_metrics(cfg, rig_trace, 0, min(arm_tick, n_done), late, step)
    active = _half_metrics(cfg, rig_trace, min(armed_at, n_done), n_done, late, step)
    end_status = loop.status()
    summary: dict[str, Any] = {
        "timing_mode": timing, "timing_reason": why,
        "wall_s": wall_s, "lockstep": result.lockstep or None,
        "duration_s": args.duration, "road": args.road, "speed_mps": args.speed,
        "controller": args.controller, "weights": loop.weight_set,
        "armed_at_s": armed_at / rate if state["armed_at"] >= 0 else None,
        "passive": passive, "active": active,
        "ratios": {k: ratio(passive, active, k)[0] for k in RATIO_KEYS
                   if k in active and k in passive},
        "faults": faults, "rearms": state["rearms"],
        "road_preview": {"state": end_status["road_preview"],
                         "trust": end_status["preview_trust"],
                         "calls": loop.preview_calls,
                         "call_fraction": loop.preview_calls / max(loop.tick_count, 1),
                         "clamps": end_status["preview_clamps"]},
        "excitation": loop.excitation_state if args.excite else None,
        "final_state": loop.lifecycle.state.name,
        "timing": loop.timing.summary(),
        "recording": str(service.recording_path) if service.recording_path else None,
        "recording_dropped": service.recorder.dropped if service.recorder else 0,
        "recording_error": service.recorder.error if service.recorder else None,
        "foxglove": service.foxglove_status(),
        "rig": result.rig_stats,
        "rig_realtime": result.rig_realtime,
        "rig_error": result.rig_error,
        "realtime": service.realtime_report.as_dict(),
        "exit_reason": service.exit_reason,
        "stopped_by": service.stop_signal or None,
    }
    if service.stop_signal:
        print(f"rig demo: stopped by {service.stop_signal} after {n_rig / rate:.2f} s of "
              f"{args.duration:g} s", file=sys.stderr)
    out = sys.stderr if args.json else sys.stdout
    print(f"\nrig demo: {args.road} at {args.speed} m/s, {args.duration:g} s "
          f"(passive, then {args.controller} bank armed at "
          f"{summary['armed_at_s'] if summary['armed_at_s'] is not None else '-'} s)", file=out)
    print(_table(passive, active), file=out)
    if lockstep:
        ls = result.lockstep
        factor = ls.get("realtime_factor", math.nan)
        factor_text = f"{factor:.2f} x" if math.isfinite(factor) and n_rig > 0 else "n/a x"
        print(f"lockstep: {n_rig / rate:.2f} s of rig time in {wall_s:.2f} s of wall time "
              f"(loop {factor_text} real time; the host held "
              f"it back {ls.get('behind_s', 0.0):.2f} s in {ls.get('stalls', 0):.0f} stalls); "
              "the lateness and step-time rows are the lockstep clock's (0)", file=out)
    pv = summary["road_preview"]
    if pv["state"] == "unused":
        print("road preview: the weight set in use calls no travel law; the stop clamp "
              f"clipped the force toward a stop in {pv['clamps']} ticks", file=out)
    elif pv["state"] != "off":
        print(f"road preview: {pv['state']} at the end (trust: {pv['trust']}), the travel "
              f"law called ahead in {100 * pv['call_fraction']:.1f} % of the ticks, the "
              f"stop clamp clipped the force in {pv['clamps']}", file=out)
    for f in faults:
        print(fault_line(f), file=out)
    if active.get("bypass_open_fraction", 0.0) > 0.5:
        print(f"note: the controller was engaged for only "
              f"{100 * (1 - active['bypass_open_fraction']):.0f} % of the second "
              f"half{' (faults above)' if faults else ''}; load average "
              f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", file=out)
    failure = service.recording_failure
    if summary["recording"]:
        print(f"recording: {failure or summary['recording']}", file=out)
    if args.json:
        print(strict_json.dumps(summary))
    # the recording was the point of --record / --excite (rig identify reads it)
    return OUTPUT_FAILED if failure and (args.record or args.excite) else 0
