"""The fixed-rate control loop: one tick = drain CAN, check, estimate, control, send.

:class:`ControlLoop` separates the work of one tick, :meth:`ControlLoop.tick` (callable
deterministically with any ``now_ns``: tests step it without sleeping, replay feeds it
recorded time), from the pacing, :meth:`ControlLoop.run` (absolute monotonic deadlines:
sleep to ``deadline - spin``, then spin; deadlines advance by exactly one period so no
drift accumulates; when the loop is more than one period late the missed deadlines are
skipped and counted).

Per tick, in this order (latency from sensor frame to valve command kept short):

1. apply at most one pending operator command (arm / disarm / reset / blending ...);
2. drain the bus: every SensorData and RigStatus is decoded and checked (CRC, rolling
   counter, ranges, status bits, rig watchdog / supply); error frames and receive
   exceptions are bus faults;
3. step the bank with the latest good SensorData (held when a frame is missing);
4. the first fault condition of the tick latches FAULT; the safe command goes out in
   this same tick together with a FaultReport frame;
5. ACTIVE: PI force loop -> spool; otherwise the safe command (Enable=0, spool 0);
6. send ValveCommand (with SensorCounterEcho); heartbeat ControllerStatus at
   ``cfg.safety.heartbeat_hz`` (FaultReport repeated with it while latched);
7. systemd watchdog ping, telemetry snapshot (``cfg.telemetry.rate_hz``) and the
   recording (non-blocking, bounded queues on their own threads).

An exception anywhere in 2-6 is caught: EXCEPTION fault, safe command.  A recording or
telemetry hand-off that raises is counted (``output_errors``, in ``status()``) and
logged, and never stops the loop or latches a fault: it is not an actuator problem.  The tick
allocates no containers in steady state (preallocated messages, decoded frame objects
and statistics) except what recording and telemetry need (docs/service.md).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import can
import numpy as np

from controller.config import RigConfig
from controller.runtime.kernels import StepFlag
from rig.bus.core import classify_bus_exception, classify_error_frame, errno_of, make_tx_message
from rig.recording.codec import TickLayout
from rig.rt.pacing import Pacer
from rig.rt.sdnotify import SdNotifier
from rig.service.lifecycle import CommandResult, Lifecycle, Transition
from rig.service.safety import DETAIL_RECV, DETAIL_SEND, FaultMonitor
from rig.service.timing import TimingStats
from rig.wire.protocol import (
    CONTROLLER_STATUS,
    FAULT_REPORT,
    RIG_STATUS,
    RIG_STATUS_ID,
    SENSOR_DATA,
    SENSOR_DATA_ID,
    VALVE_COMMAND,
    DecodeStatus,
    FaultCode,
    LifecycleState,
    RigStatus,
    SensorData,
)

__all__ = ["COMMANDS", "ControlLoop", "Recorder", "Runtime", "Telemetry",
           "tick_record_layout"]

log = logging.getLogger(__name__)

_OK = DecodeStatus.OK
_OUT_OF_RANGE = DecodeStatus.OUT_OF_RANGE
_NONE = FaultCode.NONE
_ACTIVE = LifecycleState.ACTIVE
_DEGRADED = int(StepFlag.DEGRADED)
_DIVERGED = int(StepFlag.DIVERGED)
_FAULT = LifecycleState.FAULT
_STOPPING = LifecycleState.STOPPING

#: operator commands understood by :meth:`ControlLoop.request` (argument in brackets)
COMMANDS = ("arm", "disarm", "reset", "blending", "weight_set", "road")


class Runtime(Protocol):
    """What the loop needs of ``controller.runtime.bank.BankRuntime``."""

    @property
    def flags(self) -> Any: ...
    q: np.ndarray
    firing_weight: np.ndarray
    probability: np.ndarray
    u_model: np.ndarray
    active: np.ndarray
    x_post: np.ndarray
    xf: np.ndarray

    def step(self, rattlespace_m: float, accel_mps2: float, force_meas_n: float) -> float: ...
    def reset(self) -> None: ...
    def set_blending(self, b: Any) -> None: ...
    def set_weight_set(self, w: int) -> None: ...
    def set_road(self, speed_mps: float, roughness_gd: float) -> Any: ...


class ForceLoop(Protocol):
    def step(self, force_ref_n: float, force_meas_n: float, rattlespace_m: float
             ) -> float: ...
    def reset(self) -> None: ...


class Recorder(Protocol):
    """``rig.recording.recorder.RunRecorder`` as the loop uses it (all calls non-blocking)."""

    @property
    def dropped(self) -> int: ...
    def can_frame(self, t_ns: int, tick: int, arbitration_id: int, data: bytes | bytearray,
                  is_rx: bool, error_frame: bool = False, extended_id: bool = False
                  ) -> bool: ...
    def set_tick_layout(self, layout: TickLayout) -> None: ...
    def tick_values(self, t_ns: int, scalars: Any, arrays: Any) -> bool: ...
    def event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool: ...


class Telemetry(Protocol):
    """``rig.telemetry.TelemetryPublisher`` as the loop uses it."""

    @property
    def dropped(self) -> int: ...
    def offer(self, snapshot: Any) -> bool: ...


def _bus_exception(where: str, exc: BaseException) -> dict[str, Any]:
    """The ``note`` event detail of a failed recv / send (replay raises it again)."""
    errno = errno_of(exc)
    return {"bus_exception": where, "type": type(exc).__name__, "error": str(exc),
            "errno": errno}


def tick_record_layout(rt: Runtime) -> TickLayout:
    """The loop's tick record: keys, kinds and array shapes (docs/recording.md).

    :meth:`ControlLoop._record` packs the scalars and the arrays in this order."""
    lifecycle_names = tuple(s.name for s in LifecycleState)
    top = max(FaultCode)
    fault_names = (None, *(FaultCode(v).name if v in FaultCode._value2member_map_
                           else f"UNKNOWN_{v}" for v in range(1, top + 1)))

    def arr(key: str, a: np.ndarray) -> tuple[str, str, tuple[int, ...]]:
        return (key, a.dtype.str, tuple(a.shape))   # the packer copies the native bytes

    return TickLayout((
        ("tick", "int", None),
        ("rattlespace_m", "float", None),
        ("sprung_accel_mps2", "float", None),
        ("force_meas_n", "float", None),
        ("force_ref_n", "float", None),
        ("spool_cmd", "float", None),
        ("valve_enable", "int", None),
        ("lifecycle", "enum", lifecycle_names),
        ("fault", "enum", fault_names),
        ("sensor_counter", "int", None),
        ("sensor_age_ticks", "int", None),
        ("wake_late_s", "ns_as_s", None),
        ("compute_s", "ns_as_s", None),
        ("period_s", "ns_as_s", None),
        ("overrun", "bool", None),
        ("overrun_streak", "int", None),
        ("overruns_total", "int", None),
        ("dropped_recording", "int", None),
        ("dropped_telemetry", "int", None),
        arr("q", rt.q),
        arr("firing_weight", rt.firing_weight),
        arr("probability", rt.probability),
        arr("u_model", rt.u_model),
        arr("active", rt.active),
        ("flags", "int", None),
        ("blending", "int", None),
        ("weight_set", "int", None),
        arr("x_post", rt.x_post),
        arr("xf", rt.xf),
    ))


class _Request:
    """An operator command waiting for the loop thread."""

    __slots__ = ("argument", "done", "name", "result")

    def __init__(self, name: str, argument: Any) -> None:
        self.name = name
        self.argument = argument
        self.done = threading.Event()
        self.result: CommandResult | None = None


class ControlLoop:
    """One controller service loop on one bus (see module docstring)."""

    def __init__(self, cfg: RigConfig, bus: can.BusABC, runtime: Runtime,
                 force_loop: ForceLoop, *, recorder: Recorder | None = None,
                 telemetry: Telemetry | None = None, notifier: SdNotifier | None = None,
                 blending: int = 0, weight_set: int | None = None,
                 clock_ns: Callable[[], int] = time.monotonic_ns,
                 spin_ns: int = 60_000, warmup_ticks: int | None = None,
                 timing_ring: int = 1 << 16, excitation: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.bus = bus
        self.rt = runtime
        self.pi = force_loop
        self.recorder = recorder
        self.telemetry = telemetry
        self.notifier = notifier
        self.clock_ns = clock_ns
        self.period_ns = round(1e9 / cfg.design.sample_rate_hz)
        self.spin_ns = int(spin_ns)
        rate = cfg.design.sample_rate_hz
        self.heartbeat_every = max(1, round(rate / cfg.safety.heartbeat_hz))
        self.telemetry_every = max(1, round(rate / cfg.telemetry.rate_hz))
        #: ticks of good sensor data the estimator needs after a reset before arming
        self.warmup_ticks = (round(cfg.safety.arm_warmup_s * rate) if warmup_ticks is None
                             else warmup_ticks)
        self.blending = int(blending)
        self.weight_set = int(cfg.design.weight_set if weight_set is None else weight_set)

        if recorder is not None:
            recorder.set_tick_layout(tick_record_layout(runtime))
        self.lifecycle = Lifecycle()
        self.lifecycle.add_listener(self._on_transition)
        self.monitor = FaultMonitor(cfg)
        self.timing = TimingStats(self.period_ns,
                                  round(cfg.safety.overrun_threshold_s * 1e9),
                                  ring_size=timing_ring)
        # preallocated frames
        self._valve_msg = make_tx_message(VALVE_COMMAND.frame_id)
        self._fault_msg = make_tx_message(FAULT_REPORT.frame_id)
        self._status_msg = make_tx_message(CONTROLLER_STATUS.frame_id)
        self._sd = SensorData()
        self._rs = RigStatus()
        self._requests: collections.deque[_Request] = collections.deque(maxlen=64)
        self._watchdog_period_ns = notifier.watchdog_period_ns if notifier else 0
        self.transitions: collections.deque[Transition] = collections.deque(maxlen=256)
        #: identification excitation (controller.excitation): force reference samples
        #: played once from the first arm instead of the bank's output; state one of
        #: none / pending / playing / ended / aborted (docs/identify.md)
        self.excitation = (None if excitation is None
                           else np.ascontiguousarray(excitation, dtype=np.float64))
        self.excitation_state = "none" if excitation is None else "pending"
        self.excitation_index = 0
        self.excitation_travel_m = cfg.excitation.travel_limit_m
        self.reset_state()

    # ------------------------------------------------------------------ state
    def reset_state(self) -> None:
        """Counters and held values to their start-up values (not the lifecycle)."""
        self.tick_count = 0
        self.t_ns = 0
        self._tx_valve = 0
        self._tx_fault = 0
        self._tx_status = 0
        self.rattlespace_m = 0.0
        self.force_meas_n = 0.0
        self.accel_mps2 = 0.0
        self.sensor_counter = 0
        self.force_ref_n = 0.0          # the bank's force reference (recorded in every state)
        self.cmd_force_ref_n = 0.0      # ForceReference sent (0 unless ACTIVE)
        self.spool_cmd = 0.0
        self.enable = 0
        self.bank_flags = 0
        self.degradations = 0           # times the bank's monitor degraded (not faults)
        self.good_ticks = 0          # consecutive ticks with a good SensorData since reset
        self.rx_frames = 0
        self.tx_frames = 0
        self.tx_errors = 0
        self.exceptions = 0
        self.last_exception = ""
        self.output_errors = 0          # recording / telemetry hand-offs that raised
        self.last_output_error = ""
        self.rig_bypass_open = 1
        self.rig_watchdog_tripped = 0
        self.rig_supply_ok = 1
        self.rig_status_seen = False
        self.lateness_ns = 0
        self.step_ns = 0
        self.lateness_p99_us = 0.0      # whole-run p99 lateness, refreshed per heartbeat
        self._last_wake_ns = -1
        self._last_ping_ns = -(1 << 62)

    # ------------------------------------------------------------------ commands
    def request(self, name: str, argument: Any = None,
                timeout_s: float | None = 1.0) -> CommandResult:
        """Queue an operator command for the loop thread and wait for its result.

        ``timeout_s=None`` applies it at once in the calling thread (use only when the
        loop is not running, e.g. tick-stepped tests or before :meth:`run`)."""
        if name not in COMMANDS:
            return CommandResult(False, self.lifecycle.state,
                                 f"unknown command {name!r}; one of {', '.join(COMMANDS)}")
        req = _Request(name, argument)
        if timeout_s is None:
            self._apply(req)
        else:
            self._requests.append(req)
            if not req.done.wait(timeout_s):
                return CommandResult(False, self.lifecycle.state,
                                     f"{name}: loop did not answer within {timeout_s} s")
        assert req.result is not None
        return req.result

    def _apply(self, req: _Request) -> None:
        lc, tick, t = self.lifecycle, self.tick_count, self.t_ns
        name, arg = req.name, req.argument
        try:
            if name == "arm":
                problem = self.health_problem()
                res = lc.arm(tick, t, not problem, problem)
                if res.accepted:
                    self.pi.reset()
                    if self.excitation is not None and self.excitation_state == "pending":
                        self.excitation_state = "playing"
                        self.excitation_index = 0
                        self._record_event(t, tick, "excitation", {
                            "phase": "start", "samples": int(self.excitation.shape[0]),
                            "sample_rate_hz": self.cfg.design.sample_rate_hz})
            elif name == "disarm":
                res = lc.disarm(tick, t)
            elif name == "reset":
                res = lc.reset(tick, t, self.monitor.reset_blocker(),
                               self.monitor.rig_problem())
                if res.accepted:
                    self._reset_estimation()
            elif lc.state is _ACTIVE:
                res = CommandResult(False, lc.state, f"{name}: disarm first")
            elif name == "blending":
                self.rt.set_blending(int(arg))
                self.blending = int(arg)
                res = CommandResult(True, lc.state, f"blending {self.blending}")
            elif name == "weight_set":
                self.rt.set_weight_set(int(arg))
                self.weight_set = int(arg)
                res = CommandResult(True, lc.state, f"weight set {self.weight_set}")
            else:  # road
                speed, rough = arg
                self.rt.set_road(float(speed), float(rough))
                res = CommandResult(True, lc.state, f"road {speed} m/s, Gd {rough}")
        except Exception as exc:  # bad argument: refuse, never disturb the loop
            res = CommandResult(False, lc.state, f"{name}: {exc}")
        req.result = res
        req.done.set()
        log.info("command %s(%s): %s", name, "" if arg is None else arg, res.message)
        self._record_event(t, tick, "command",
                           {"command": name, "argument": arg, **res.as_dict()})

    def health_problem(self) -> str:
        """'' when arming is allowed, else the reason."""
        problem = self.monitor.health_problem()
        if problem:
            return problem
        if self.good_ticks < self.warmup_ticks:
            return f"estimator warming up ({self.good_ticks}/{self.warmup_ticks} ticks)"
        if not self.rig_supply_ok:
            return "rig reports hydraulic supply loss"
        return ""

    def _reset_estimation(self) -> None:
        self.rt.reset()
        self.pi.reset()
        self.monitor.reset_estimator_checks()
        self.good_ticks = 0

    def _on_transition(self, tr: Transition) -> None:
        self.transitions.append(tr)
        if self.excitation_state == "playing" and tr.state is not _ACTIVE:
            self._end_excitation(tr.t_ns, tr.tick, "aborted", tr.reason)
        self._record_event(tr.t_ns, tr.tick, "fault" if tr.state is _FAULT else "lifecycle",
                           tr.as_dict())
        try:
            if self.telemetry is not None:
                self.telemetry.offer(self.snapshot())
            if self.notifier is not None:
                self.notifier.status(f"{tr.state.name}: {tr.reason}")
        except Exception as exc:
            self._on_output_error(exc)

    def _end_excitation(self, t_ns: int, tick: int, how: str, reason: str) -> None:
        """The excitation stops (``how``: ended / aborted): marked in the recording."""
        self.excitation_state = how
        self._record_event(t_ns, tick, "excitation", {
            "phase": "end" if how == "ended" else "aborted", "reason": reason,
            "samples_played": self.excitation_index})

    def _excite(self, now_ns: int, tick: int) -> float:
        """The excitation's force reference of this ACTIVE tick; at its end (or beyond
        the travel limit) the loop disarms (valve safe) and the segment is marked."""
        exc = self.excitation
        assert exc is not None
        i = self.excitation_index
        if abs(self.rattlespace_m) > self.excitation_travel_m:
            self.lifecycle.disarm(tick, now_ns, "excitation: travel limit "
                                  f"{self.excitation_travel_m} m exceeded")
            return 0.0
        if i >= exc.shape[0]:
            self._end_excitation(now_ns, tick, "ended", "complete")
            self.lifecycle.disarm(tick, now_ns, "excitation complete")
            return 0.0
        self.excitation_index = i + 1
        return float(exc[i])

    def _record_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> None:
        """An event to the recording; a failing recorder never disturbs the loop."""
        if self.recorder is not None:
            try:
                self.recorder.event(t_ns, tick, kind, detail)
            except Exception as exc:
                self._on_output_error(exc)

    # ------------------------------------------------------------------ one tick
    def tick(self, now_ns: int, lateness_ns: int = 0) -> None:
        """Do the work of one tick at time ``now_ns`` (``lateness_ns`` behind its deadline).

        Never raises: any exception becomes an EXCEPTION fault with the safe command."""
        self.t_ns = now_ns
        tick = self.tick_count
        mon = self.monitor
        lc = self.lifecycle
        timing = self.timing
        timing.start_tick(lateness_ns)
        self.lateness_ns = lateness_ns
        if self._requests:
            self._apply(self._requests.popleft())
        mon.begin_tick()
        try:
            self._receive(now_ns, tick)
            mon.end_receive()
            if mon.fresh:
                self.good_ticks += 1
            elif not mon.sensor_seen:
                self.good_ticks = 0
            if mon.sensor_seen:
                rt = self.rt
                force_ref = rt.step(self.rattlespace_m, self.accel_mps2, self.force_meas_n)
                flags = int(rt.flags)
                if (flags ^ self.bank_flags) & _DEGRADED:
                    self._on_degraded_change(flags, now_ns, tick)
                self.bank_flags = flags
                if self.excitation_state == "playing":
                    # the bank is not in the loop while the excitation plays (and is
                    # designed for the rig being identified): its divergence monitor
                    # is no actuator fault; sensor, bus, timing faults still latch
                    mon.estimator(flags & ~_DIVERGED, 0.0)
                else:
                    mon.estimator(flags, force_ref)
                if flags & 3:               # estimator state unusable: restart it warm
                    rt.reset()
                    self.good_ticks = 0
            else:
                force_ref = 0.0
            mon.overrun(timing.overrun_streak)
            spool = 0.0
            if mon.code is not _NONE:
                self._latch(mon.code, mon.detail, now_ns)
            if lc.state is _ACTIVE and self.excitation_state == "playing":
                force_ref = self._excite(now_ns, tick)
            if lc.state is _ACTIVE:
                spool = self.pi.step(force_ref, self.force_meas_n, self.rattlespace_m)
                mon.output(spool)
                if mon.code is not _NONE:
                    self._latch(mon.code, mon.detail, now_ns)
            self.force_ref_n = force_ref
            if lc.state is _ACTIVE:
                self.enable = 1
                self.spool_cmd = spool
                self.cmd_force_ref_n = force_ref
            else:
                self.enable = 0
                self.spool_cmd = 0.0
                self.cmd_force_ref_n = 0.0
            self._send_valve(now_ns, tick)
        except Exception as exc:
            self._on_exception(exc, now_ns, tick)
        try:
            if tick % self.heartbeat_every == 0:
                self._heartbeat(now_ns, tick)
        except Exception as exc:
            self._on_exception(exc, now_ns, tick)
        mon.end_tick()
        wd = self._watchdog_period_ns
        if wd and now_ns - self._last_ping_ns >= wd:
            self._last_ping_ns = now_ns
            self.notifier.watchdog()  # type: ignore[union-attr]
        self.step_ns = self.clock_ns() - now_ns
        timing.end_tick(self.step_ns)
        if (tick + 1) % self.heartbeat_every == 0:
            # for the next tick's heartbeat, computed here after the valve command went
            # out: a few numpy calls, tens of microseconds with cold caches
            self.lateness_p99_us = timing.lateness_p99_us()
        try:
            if self.recorder is not None:
                self._record(now_ns, tick)
            if self.telemetry is not None and tick % self.telemetry_every == 0:
                self.telemetry.offer(self.snapshot())
        except Exception as exc:    # the outputs never stop the control loop
            self._on_output_error(exc)
        self.tick_count = tick + 1

    def _on_output_error(self, exc: Exception) -> None:
        """A recording / telemetry hand-off raised: counted, logged (the first and then
        every 1000th), shown in ``status()``; the valve command of the tick is out."""
        self.output_errors += 1
        self.last_output_error = f"{type(exc).__name__}: {exc}"
        if self.output_errors % 1000 == 1:
            log.error("recording/telemetry hand-off failed (%d so far): %s",
                      self.output_errors, self.last_output_error)

    def _on_exception(self, exc: Exception, now_ns: int, tick: int) -> None:
        self.exceptions += 1
        self.last_exception = f"{type(exc).__name__}: {exc}"
        self.monitor.exception()
        if self.lifecycle.state is not _STOPPING:
            self._latch(FaultCode.EXCEPTION, 0, now_ns, self.last_exception)
        else:
            log.exception("exception while stopping")
        self.enable = 0
        self.spool_cmd = 0.0
        self.cmd_force_ref_n = 0.0
        try:
            self._send_valve(now_ns, tick)
        except Exception:
            log.exception("could not send the safe valve command")

    def _receive(self, now_ns: int, tick: int) -> None:
        bus = self.bus
        mon = self.monitor
        rec = self.recorder
        sd, rs = self._sd, self._rs
        while True:
            try:
                msg = bus.recv(0.0)
            except (can.CanError, OSError) as exc:
                mon.bus_error(classify_bus_exception(exc), DETAIL_RECV)
                self._record_event(now_ns, tick, "note", _bus_exception("recv", exc))
                return
            if msg is None:
                return
            self.rx_frames += 1
            if rec is not None:
                try:
                    rec.can_frame(now_ns, tick, msg.arbitration_id, msg.data, True,
                                  msg.is_error_frame, msg.is_extended_id)
                except Exception as exc:
                    self._on_output_error(exc)
            if msg.is_error_frame:
                code = classify_error_frame(msg)
                if code is not _NONE:
                    mon.bus_error(code, msg.arbitration_id & 0xFF)
                continue
            fid = msg.arbitration_id
            if fid == SENSOR_DATA_ID and not msg.is_extended_id:
                st = SENSOR_DATA.decode(msg.data, sd)
                if st is _OK:
                    if mon.sensor_frame(True, sd.counter, sd.sensor_status, sd.rattlespace_m,
                                        sd.load_cell_force_n, sd.sprung_accel_mps2):
                        self.rattlespace_m = sd.rattlespace_m
                        self.force_meas_n = sd.load_cell_force_n
                        self.accel_mps2 = sd.sprung_accel_mps2
                        self.sensor_counter = sd.counter
                else:
                    mon.sensor_frame(False, 0, 0, 0.0, 0.0, 0.0)
            elif fid == RIG_STATUS_ID and not msg.is_extended_id:
                st = RIG_STATUS.decode(msg.data, rs)
                if st is _OK or st is _OUT_OF_RANGE:
                    self.rig_status_seen = True
                    self.rig_bypass_open = rs.bypass_open
                    self.rig_watchdog_tripped = rs.watchdog_tripped
                    self.rig_supply_ok = rs.supply_ok
                    mon.rig_status(True, rs.counter, bool(rs.watchdog_tripped),
                                   bool(rs.supply_ok))
                else:
                    mon.rig_status(False, 0, False, True)

    def _on_degraded_change(self, flags: int, now_ns: int, tick: int) -> None:
        """The bank's estimator monitor degraded or re-armed (not a fault): count, log at
        most every 1000th, and record a note."""
        degraded = bool(flags & _DEGRADED)
        if degraded:
            self.degradations += 1
        if self.degradations % 1000 == 1 or not degraded:
            log.warning("estimator %s (%d degradations so far)",
                        "degraded: conservative law" if degraded else "re-armed",
                        self.degradations)
        self._record_event(now_ns, tick, "note",
                           {"estimator": "degraded" if degraded else "re-armed",
                            "degradations": self.degradations})

    def _latch(self, code: FaultCode, detail: int, now_ns: int, message: str = "") -> None:
        """Latch FAULT (if not already) and send the FaultReport now."""
        lc = self.lifecycle
        if lc.state is _FAULT or lc.state is _STOPPING:
            return
        if not message:
            message = self._describe(code, detail)
        lc.fault(code, self.tick_count, now_ns, detail, message)
        self.pi.reset()
        self._send_fault_report(now_ns, self.tick_count)

    def _describe(self, code: FaultCode, detail: int) -> str:
        """A human-readable fault message (only when a fault latches)."""
        if code is FaultCode.EXCEPTION:
            return self.last_exception or "exception"
        return (f"detail {detail}; sensors rs={self.rattlespace_m:.6g} m "
                f"F={self.force_meas_n:.6g} N a={self.accel_mps2:.6g} m/s2, "
                f"age {self.monitor.sensor_age_ticks} ticks, flags {self.bank_flags}")

    def _send(self, msg: can.Message, now_ns: int, tick: int) -> bool:
        try:
            self.bus.send(msg, 0.0)
        except (can.CanError, OSError) as exc:
            self.tx_errors += 1
            self.monitor.bus_error(classify_bus_exception(exc), DETAIL_SEND)
            self._record_event(now_ns, tick, "note", {
                **_bus_exception("send", exc), "arbitration_id": msg.arbitration_id})
            return False
        self.tx_frames += 1
        rec = self.recorder
        if rec is not None:
            try:
                rec.can_frame(now_ns, tick, msg.arbitration_id, msg.data, False)
            except Exception as exc:
                self._on_output_error(exc)
        return True

    def _send_valve(self, now_ns: int, tick: int) -> None:
        msg = self._valve_msg
        VALVE_COMMAND.encode(msg.data, self._tx_valve, self.enable, int(self.lifecycle.state),
                             self.spool_cmd, self.cmd_force_ref_n, self.sensor_counter)
        self._tx_valve += 1
        if not self._send(msg, now_ns, tick) and self.enable:
            # the command did not go out: the fault latches now, the next tick is safe
            self._latch(self.monitor.code or FaultCode.BUS_ERROR, DETAIL_SEND, now_ns)

    def _send_fault_report(self, now_ns: int, tick: int) -> None:
        lc = self.lifecycle
        msg = self._fault_msg
        FAULT_REPORT.encode(msg.data, self._tx_fault, int(lc.state), int(lc.fault_code),
                            max(lc.fault_tick, 0), lc.fault_detail)
        self._tx_fault += 1
        self._send(msg, now_ns, tick)

    def _heartbeat(self, now_ns: int, tick: int) -> None:
        lc = self.lifecycle
        msg = self._status_msg
        p99_s = self.lateness_p99_us * 1e-6
        active_fault = lc.fault_code
        if active_fault is _NONE and self.bank_flags & _DEGRADED:
            active_fault = FaultCode.ESTIMATOR_DEGRADED
        CONTROLLER_STATUS.encode(msg.data, self._tx_status, int(lc.state), int(active_fault),
                                 self.timing.overruns & 0xFFFF, self.blending & 0xF,
                                 self.weight_set & 0xF, min(p99_s, 0.065535))
        self._tx_status += 1
        self._send(msg, now_ns, tick)
        if lc.state is _FAULT:
            self._send_fault_report(now_ns, tick)

    # ------------------------------------------------------------------ outputs
    def _record(self, now_ns: int, tick: int) -> None:
        """One tick record per tick, packed (fields: :func:`tick_record_layout`)."""
        rt = self.rt
        timing = self.timing
        lc = self.lifecycle
        wake_prev = self._last_wake_ns
        self._last_wake_ns = now_ns
        rec = self.recorder
        assert rec is not None
        tel = self.telemetry
        lateness = self.lateness_ns
        rec.tick_values(now_ns, (
            tick, self.rattlespace_m, self.accel_mps2, self.force_meas_n, self.force_ref_n,
            self.spool_cmd, self.enable, lc.state, lc.fault_code, self.sensor_counter,
            self.monitor.sensor_age_ticks, lateness, self.step_ns,
            now_ns - wake_prev if wake_prev >= 0 else -1,
            lateness > timing.overrun_threshold_ns, timing.overrun_streak, timing.overruns,
            rec.dropped, tel.dropped if tel is not None else 0,
            self.bank_flags, self.blending, self.weight_set,
        ), (rt.q, rt.firing_weight, rt.probability, rt.u_model, rt.active, rt.x_post, rt.xf))

    def snapshot(self) -> dict[str, Any]:
        """Telemetry snapshot (``cfg.telemetry.rate_hz`` and at every transition).

        Layout agreed with ``rig.telemetry`` (docs/service.md, docs/telemetry.md):
        ``tick``, ``t_ns``, ``lifecycle``, ``fault`` and the sub-objects ``state`` and
        ``timing`` (plain Python values; built only at the telemetry rate)."""
        lc = self.lifecycle
        timing = self.timing
        rt = self.rt
        return {
            "tick": self.tick_count,
            "t_ns": self.t_ns,
            "lifecycle": lc.state.name,
            "fault": None if lc.fault_code is _NONE else {
                "code": lc.fault_code.name, "tick": lc.fault_tick,
                "detail": lc.fault_detail, "message": lc.fault_message},
            "state": {
                "rattlespace_m": self.rattlespace_m,
                "sprung_accel_mps2": self.accel_mps2,
                "force_meas_n": self.force_meas_n,
                "force_ref_n": self.force_ref_n,
                "spool_cmd": self.spool_cmd,
                "valve_enable": self.enable,
                "sensor_counter": self.sensor_counter,
                "firing_weight": rt.firing_weight.tolist(),
                "q": rt.q.tolist(),
                "flags": self.bank_flags,
                "blending": self.blending,
                "weight_set": self.weight_set,
            },
            "timing": {
                "wake_late_s": self.lateness_ns * 1e-9,
                "compute_s": self.step_ns * 1e-9,
                "lateness_p99_s": self.lateness_p99_us * 1e-6,
                "max_lateness_s": timing.max_lateness_ns * 1e-9,
                "max_compute_s": timing.max_step_ns * 1e-9,
                "overruns": timing.overruns,
                "misses": timing.misses,
                "skipped": timing.skipped,
                "dropped_recording": (self.recorder.dropped
                                      if self.recorder is not None else 0),
            },
        }

    def status(self) -> dict[str, Any]:
        """Full status (off the hot path: the telemetry thread's status provider)."""
        lc = self.lifecycle
        return {
            "lifecycle": lc.state.name,
            "fault": lc.fault_code.name,
            "fault_tick": lc.fault_tick,
            "fault_detail": lc.fault_detail,
            "fault_message": lc.fault_message,
            "condition": self.monitor.condition.name,
            "estimator_degraded": bool(self.bank_flags & _DEGRADED),
            "estimator_degradations": self.degradations,
            "health": self.health_problem() or "ok",
            "tick": self.tick_count,
            "blending": self.blending,
            "weight_set": self.weight_set,
            "rx_frames": self.rx_frames,
            "tx_frames": self.tx_frames,
            "tx_errors": self.tx_errors,
            "exceptions": self.exceptions,
            "output_errors": self.output_errors,
            "last_output_error": self.last_output_error,
            "timing": self.timing.summary(),
            "dropped_recording": self.recorder.dropped if self.recorder is not None else 0,
            "dropped_telemetry": self.telemetry.dropped if self.telemetry is not None else 0,
        }

    # ------------------------------------------------------------------ pacing
    def run(self, stop: threading.Event, max_ticks: int | None = None,
            on_tick: Callable[[ControlLoop], None] | None = None,
            duration_s: float | None = None) -> None:
        """Tick at the configured rate until ``stop`` is set, ``max_ticks`` ticks were
        done or ``duration_s`` of wall time has passed (skipped deadlines included).

        ``on_tick`` (if given) runs after each tick in the loop thread: keep it cheap.
        Pacing: :class:`rig.rt.pacing.Pacer` (absolute deadlines, missed ones skipped
        once a whole period is lost), the same rule as the emulated rig's."""
        clock = self.clock_ns
        period = self.period_ns
        pacer = Pacer(period, start_ns=clock() + period, spin_ns=self.spin_ns, clock=clock)
        timing = self.timing
        end = None if max_ticks is None else self.tick_count + max_ticks
        end_ns = (None if duration_s is None
                  else pacer.deadline + round(duration_s * 1e9) - period)
        while not stop.is_set():
            now = pacer.wait()
            self.tick(now, now - pacer.deadline)
            if on_tick is not None:
                on_tick(self)
            missed = pacer.advance()
            if missed:
                timing.add_skipped(missed)
            if end is not None and self.tick_count >= end:
                break
            if end_ns is not None and pacer.deadline > end_ns:
                break

    def shutdown(self, reason: str = "shutdown") -> None:
        """STOPPING: the safe valve command and a SHUTDOWN FaultReport go out."""
        now = self.clock_ns()
        lc = self.lifecycle
        lc.stop(self.tick_count, now, reason)
        self.enable = 0
        self.spool_cmd = 0.0
        self.cmd_force_ref_n = 0.0
        try:
            self._send_valve(now, self.tick_count)
            msg = self._fault_msg
            FAULT_REPORT.encode(msg.data, self._tx_fault, int(_STOPPING),
                                int(FaultCode.SHUTDOWN), self.tick_count & 0xFFFFFFFF, 0)
            self._tx_fault += 1
            self._send(msg, now, self.tick_count)
            self.lateness_p99_us = self.timing.lateness_p99_us()
            self._heartbeat(now, self.tick_count)
        except Exception:
            log.exception("could not send the shutdown frames")
