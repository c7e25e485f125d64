"""The fixed-rate control loop: one tick = drain CAN, check, estimate, control, send.

:class:`ControlLoop` separates the work of one tick, :meth:`ControlLoop.tick` (callable
deterministically with any ``now_ns``: tests step it without sleeping, replay feeds it
recorded time), from the pacing, :meth:`ControlLoop.run` (absolute monotonic deadlines:
sleep to ``deadline - spin``, then spin; deadlines advance by exactly one period so no
drift accumulates; when the loop is more than one period late the missed deadlines are
skipped and counted).

The parts, ros2_control-style: the hardware interface
:class:`rig.service.hardware.RigIO` reads the rig's frames and writes the controller's
(``read`` / ``write_*``); the update is the runtime bank's step and the PI force loop
(the ``Runtime`` and ``ForceLoop`` seams of :mod:`rig.service.seams`, with the recorder
and telemetry seams); :class:`ControlLoop` is the
manager: lifecycle, fault monitor, operator commands (:mod:`rig.operator_commands`), pacing and
the outputs (recording, telemetry).

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
7. systemd watchdog ping; the step time ends here.  Then the outputs: the tick's CAN
   frames to the recording (:meth:`rig.service.hardware.RigIO.record_frames`), and
   the tick record, packed once (:class:`rig.recording.codec.TickPacker`) and the same
   bytes handed to the recording (its writer process) and, every ``telemetry_every``
   ticks, to the telemetry process (Zenoh and the live Foxglove view;
   :mod:`rig.telemetry_process`), both non-blocking pipes that drop and count.  Every
   ``telemetry_every`` ticks, before 1., the telemetry process's operator commands are
   taken (at most one, validated again) and the process's losses recorded.

An exception anywhere in 2-6 is caught: EXCEPTION fault, safe command.  A recording or
telemetry hand-off that raises is counted (``output_errors``, in ``status()``) and
logged, and never stops the loop or latches a fault: it is not an actuator problem.  The tick
allocates no containers in steady state (preallocated messages, decoded frame objects
and statistics) except what recording and telemetry need (docs/service.md).
"""

from __future__ import annotations

import collections
import logging
import math
import operator
import threading
import time
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from controller.config import RigConfig
from controller.road_preview import cached_road_preview
from controller.runtime.kernels import StepFlag
from rig.operator_commands import OPERATOR_COMMANDS
from rig.recording.codec import TickLayout, TickPacker
from rig.rt.pacing import LOOP_SPIN_NS, Pacer, TickPacer
from rig.rt.sdnotify import SdNotifier
from rig.service.hardware import RigIO
from rig.service.host_lateness import PeerLateness, assess
from rig.service.lifecycle import CommandResult, Lifecycle, Transition
from rig.service.road_preview_stream import RoadPreviewStream
from rig.service.safety import DETAIL_SEND, FaultMonitor
from rig.service.seams import ForceLoop, Recorder, Runtime, Telemetry
from rig.service.timing import TimingStats
from rig.wire.protocol import (
    DecodeStatus,
    FaultCode,
    LifecycleState,
)

__all__ = ["TICK_RECORD_FIELDS", "ControlLoop", "tick_record_layout"]

log = logging.getLogger(__name__)

_OK = DecodeStatus.OK
_OUT_OF_RANGE = DecodeStatus.OUT_OF_RANGE
_NONE = FaultCode.NONE
_ACTIVE = LifecycleState.ACTIVE
_DEGRADED = int(StepFlag.DEGRADED)
_DIVERGED = int(StepFlag.DIVERGED)
_STOP_DEGRADED = int(StepFlag.STOP_DEGRADED)
_STOP_CONTACT = int(StepFlag.STOP_CONTACT)
_STOP_BITS = _STOP_DEGRADED | _STOP_CONTACT
_RIDE_HEIGHT = int(StepFlag.RIDE_HEIGHT)
_FAULT = LifecycleState.FAULT
_STOPPING = LifecycleState.STOPPING

#: The loop's tick record in record order (docs/recording.md): (key, kind, where the
#: loop holds the value as an attribute path).  Kind "array" takes dtype and shape from
#: the runtime's array; "enum" names come from the wire enums.  :func:`tick_record_layout`
#: and :meth:`ControlLoop._record` both read this one table.
TICK_RECORD_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("tick", "int", "tick_count"),
    ("rattlespace_m", "float", "io.rattlespace_m"),
    ("sprung_accel_mps2", "float", "io.accel_mps2"),
    ("force_meas_n", "float", "io.force_meas_n"),
    ("force_ref_n", "float", "force_ref_n"),
    ("spool_cmd", "float", "spool_cmd"),
    ("valve_enable", "int", "enable"),
    ("lifecycle", "enum", "lifecycle.state"),
    ("fault", "enum", "lifecycle.fault_code"),
    ("sensor_counter", "int", "io.sensor_counter"),
    ("sensor_age_ticks", "int", "monitor.sensor_age_ticks"),
    ("wake_late_s", "ns_as_s", "lateness_ns"),
    ("compute_s", "ns_as_s", "step_ns"),
    ("period_s", "ns_as_s", "wake_interval_ns"),
    ("overrun", "bool", "overrun"),
    ("overrun_streak", "int", "timing.overrun_streak"),
    ("overruns_total", "int", "timing.overruns"),
    ("dropped_recording", "int", "recording_dropped"),
    ("dropped_telemetry", "int", "telemetry_dropped"),
    ("q", "array", "rt.running.q"),
    ("firing_weight", "array", "rt.running.firing_weight"),
    ("probability", "array", "rt.running.probability"),
    ("u_model", "array", "rt.running.u_model"),
    ("active", "array", "rt.running.active"),
    ("models", "array", "rt.running.models"),
    ("flags", "int", "bank_flags"),
    ("blending", "int", "blending"),
    ("weight_set", "int", "weight_set"),
    ("sprung_mass_est_kg", "float", "rt.sprung_mass_est_kg"),
    ("spring_rate_est_n_per_m", "float", "rt.spring_rate_est_n_per_m"),
    ("damping_est_ns_per_m", "float", "rt.damping_est_ns_per_m"),
    ("wheel_hop_hz", "float", "rt.wheel_hop_hz"),
    ("tire_stiffness_est", "float", "rt.tire_stiffness_est"),
    ("x_post", "array", "rt.running.x_post"),
    ("xf", "array", "rt.xf"),
    ("stop_contact_s", "float", "rt.stop_contact_s"),
    ("stop_degraded", "bool", "stop_degraded"),
    ("comfort_share", "float", "rt.comfort_share"),
    ("ride_height_m", "float", "rt.ride_height_m"),
)


def _enum_names(key: str) -> tuple[str, ...]:
    if key == "lifecycle":
        return tuple(s.name for s in LifecycleState)
    top = max(FaultCode)
    return ("", *(FaultCode(v).name if v in FaultCode._value2member_map_
                    else f"UNKNOWN_{v}" for v in range(1, top + 1)))


def tick_record_layout(rt: Runtime) -> TickLayout:
    """The loop's tick record (:data:`TICK_RECORD_FIELDS`): keys, kinds and array shapes
    of ``rt``'s arrays (the packer copies their native bytes)."""
    fields: list[tuple[str, str, Any]] = []
    for key, kind, source in TICK_RECORD_FIELDS:
        if kind == "array":
            a = np.asarray(operator.attrgetter(source.removeprefix("rt."))(rt))
            fields.append((key, a.dtype.str, tuple(a.shape)))
        else:
            fields.append((key, kind, _enum_names(key) if kind == "enum" else None))
    return TickLayout(tuple(fields))


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
                 spin_ns: int = LOOP_SPIN_NS, warmup_ticks: int | None = None,
                 timing_ring: int = 1 << 16, excitation: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.rt = runtime
        self.pi = force_loop
        self._recorder = recorder
        #: the telemetry process (Zenoh and the live Foxglove view), fed every
        #: ``telemetry_every`` ticks (its ``tick_every``)
        self.telemetry = telemetry
        self.notifier = notifier
        self.clock_ns = clock_ns
        self.period_ns = round(1e9 / cfg.design.sample_rate_hz)
        self.spin_ns = int(spin_ns)
        rate = cfg.design.sample_rate_hz
        self.heartbeat_every = max(1, round(rate / cfg.safety.heartbeat_hz))
        self.telemetry_every = (max(1, round(rate / cfg.telemetry.rate_hz))
                                if telemetry is None else telemetry.tick_every)
        #: ticks of good sensor data the estimator needs after a reset before arming
        self.warmup_ticks = (round(cfg.safety.arm_warmup_s * rate) if warmup_ticks is None
                             else warmup_ticks)
        self.blending = int(blending)
        self.weight_set = int(cfg.design.weight_set if weight_set is None else weight_set)
        #: not '' = every arm is refused with this reason (a failed required host check)
        self.arm_blocker = ""
        #: how late the peer (the emulated rig) was, asked when a SENSOR_STALE latches
        #: (rig/service/host_lateness.py); None: no peer to ask (a real rig)
        self.peer_lateness: PeerLateness | None = None
        #: the rig's drive watchdog [ns] when known (the emulated rig's), for attributing a
        #: RIG_WATCHDOG to the loop's lateness; 0: unknown
        self.peer_watchdog_ns = 0

        #: the tick record, packed once per tick for the recording and the telemetry
        self._packer = TickPacker(tick_record_layout(runtime))
        if recorder is not None:
            recorder.set_tick_layout(self._packer.layout)
        self._record_scalars = operator.attrgetter(
            *(src for _k, kind, src in TICK_RECORD_FIELDS if kind != "array"))
        self._record_arrays = operator.attrgetter(
            *(src for _k, kind, src in TICK_RECORD_FIELDS if kind == "array"))
        self.lifecycle = Lifecycle()
        self.lifecycle.add_listener(self._on_transition)
        self.monitor = FaultMonitor(cfg)
        self.timing = TimingStats(self.period_ns,
                                  round(cfg.safety.overrun_threshold_s * 1e9),
                                  ring_size=timing_ring)
        #: hardware interface: frames in (read) and out (write)
        self.io = RigIO(bus, self.monitor, recorder,
                        lambda t, k, detail: self._record_event(t, k, "note", detail),
                        self._on_output_error)
        #: road preview (controller/road_preview.py, design.preview_*): the predictor and
        #: the road ahead from the rig's RoadPreview frames; None when it is off
        #: (built for every weight set: the operator may select the schedule or the
        #: governed comfort set at run time)
        self.road_preview = cached_road_preview(cfg)
        self.preview_stream = (None if self.road_preview is None
                               else RoadPreviewStream(self.road_preview.horizon_ticks))
        self.io.preview = self.preview_stream
        self.preview_live = False
        self.preview_calls = 0          # ticks in which the preview called the travel law
        self._requests: collections.deque[_Request] = collections.deque(maxlen=64)
        #: one handler per operator command (rig.operator_commands owns the table)
        self._handlers: dict[str, Callable[[Any], CommandResult]] = {
            "arm": self._arm, "disarm": self._disarm, "reset": self._reset,
            "blending": self._set_blending, "weight_set": self._set_weight_set,
            "road": self._set_road}
        assert self._handlers.keys() == OPERATOR_COMMANDS.keys(), "rig.operator_commands changed"
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

    @property
    def recorder(self) -> Recorder | None:
        """The run's recorder (None: not recording); the hardware interface records the
        frames it reads and writes into the same one."""
        return self._recorder

    @recorder.setter
    def recorder(self, recorder: Recorder | None) -> None:
        self._recorder = recorder
        self.io.recorder = recorder
        if recorder is not None:
            recorder.set_tick_layout(self._packer.layout)

    # the hardware interface's read-outs, for status, telemetry and the operator's view
    bus = property(operator.attrgetter("io.bus"), doc="the CAN bus")
    rattlespace_m = property(operator.attrgetter("io.rattlespace_m"),
                             doc="last good LVDT rattlespace [m]")
    force_meas_n = property(operator.attrgetter("io.force_meas_n"),
                            doc="last good load-cell force [N]")
    accel_mps2 = property(operator.attrgetter("io.accel_mps2"),
                          doc="last good sprung-mass acceleration [m/s^2]")
    sensor_counter = property(operator.attrgetter("io.sensor_counter"),
                              doc="rolling counter of the last good SensorData")
    rig_supply_ok = property(operator.attrgetter("io.rig_supply_ok"),
                             doc="the rig's last RigStatus reported hydraulic supply")
    rx_frames = property(operator.attrgetter("io.rx_frames"), doc="frames received")
    tx_frames = property(operator.attrgetter("io.tx_frames"), doc="frames sent")
    tx_errors = property(operator.attrgetter("io.tx_errors"), doc="sends that failed")

    # ------------------------------------------------------------------ state
    def reset_state(self) -> None:
        """Counters and held values to their start-up values (not the lifecycle)."""
        self.tick_count = 0
        self.t_ns = 0
        self.io.reset()
        self.force_ref_n = 0.0          # the bank's force reference (recorded in every state)
        self.cmd_force_ref_n = 0.0      # ForceReference sent (0 unless ACTIVE)
        self.enable, self.spool_cmd = 0, 0.0   # the safe command until the first tick
        self.bank_flags = 0
        self.degradations = 0           # times the bank's monitor degraded (not faults)
        self.stop_degradations = 0      # times the stop-contact monitor degraded (not faults)
        self.stop_contact_episodes = 0  # bump-stop contact episodes seen
        self._episode_start_tick = -1   # tick the current contact episode started (-1: none)
        self.off_centre_episodes = 0    # times the ride-height monitor found the body off centre
        self.good_ticks = 0          # consecutive ticks with a good SensorData since reset
        self.exceptions = 0
        self.last_exception = ""
        self.output_errors = 0          # recording / telemetry hand-offs that raised
        self.last_output_error = ""
        self.lateness_ns = 0
        self.step_ns = 0
        self.lateness_p99_us = 0.0      # whole-run p99 lateness, refreshed per heartbeat
        self._last_wake_ns = -1
        self.wake_interval_ns = -1      # since the previous tick's wake-up (-1: first tick)
        self.overrun = False            # this tick woke later than the overrun threshold
        self.recording_dropped = 0
        self.telemetry_dropped = 0
        self._last_ping_ns = -(1 << 62)

    # ------------------------------------------------------------------ commands
    def request(self, name: str, argument: Any = None,
                timeout_s: float | None = 1.0) -> CommandResult:
        """Queue an operator command for the loop thread and wait for its result.

        ``timeout_s=None`` applies it at once in the calling thread (use only when the
        loop is not running, e.g. tick-stepped tests or before :meth:`run`)."""
        if name not in OPERATOR_COMMANDS:
            return CommandResult(False, self.lifecycle.state,
                                 f"unknown command {name!r}; one of "
                                 f"{', '.join(OPERATOR_COMMANDS)}")
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
            if OPERATOR_COMMANDS[name].needs_inactive and lc.state is _ACTIVE:
                res = CommandResult(False, lc.state, f"{name}: disarm first")
            else:
                res = self._handlers[name](arg)
        except Exception as exc:  # bad argument: refuse, never disturb the loop
            res = CommandResult(False, lc.state, f"{name}: {exc}")
        req.result = res
        req.done.set()
        log.info("command %s(%s): %s", name, "" if arg is None else arg, res.message)
        self._record_event(t, tick, "command",
                           {"command": name, "argument": arg, **res.as_dict()})

    def _arm(self, _arg: None) -> CommandResult:
        problem = self.arm_blocker or self.health_problem()
        tick, t = self.tick_count, self.t_ns
        res = self.lifecycle.arm(tick, t, not problem, problem)
        if res.accepted:
            self.pi.reset()
            if self.excitation is not None and self.excitation_state == "pending":
                self.excitation_state = "playing"
                self.excitation_index = 0
                self._record_event(t, tick, "excitation", {
                    "phase": "start", "samples": int(self.excitation.shape[0]),
                    "sample_rate_hz": self.cfg.design.sample_rate_hz})
        return res

    def _disarm(self, _arg: None) -> CommandResult:
        return self.lifecycle.disarm(self.tick_count, self.t_ns)

    def _reset(self, _arg: None) -> CommandResult:
        res = self.lifecycle.reset(self.tick_count, self.t_ns, self.monitor.reset_blocker(),
                                   self.monitor.rig_problem())
        if res.accepted:
            self._reset_estimation()
        return res

    def _set_blending(self, blending: int) -> CommandResult:
        self.rt.set_blending(int(blending))
        self.blending = int(blending)
        return CommandResult(True, self.lifecycle.state, f"blending {self.blending}")

    def _set_weight_set(self, weight_set: int) -> CommandResult:
        self.rt.set_weight_set(int(weight_set))
        self.weight_set = int(weight_set)
        return CommandResult(True, self.lifecycle.state, f"weight set {self.weight_set}")

    def _set_road(self, road: tuple[float, float]) -> CommandResult:
        speed, rough = road
        self.rt.set_road(float(speed), float(rough))
        return CommandResult(True, self.lifecycle.state, f"road {speed} m/s, Gd {rough}")

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

    def record_note(self, detail: Any) -> None:
        """A ``note`` event at the current tick (e.g. the telemetry process was lost);
        the loop thread's, or before the loop runs."""
        self._record_event(self.t_ns, self.tick_count, "note", detail)

    def _record_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> None:
        """An event to the recording and the telemetry process; a failing output never
        disturbs the loop.  The frames noted before it are recorded first (their order)."""
        if self.recorder is not None:
            self.io.record_frames()
            try:
                self.recorder.event(t_ns, tick, kind, detail)
            except Exception as exc:
                self._on_output_error(exc)
        if self.telemetry is not None:
            try:
                self.telemetry.offer_event(t_ns, tick, kind, detail)
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
        tel = self.telemetry
        if tel is not None and tick % self.telemetry_every == 0:
            # the telemetry process's notes and at most one of its commands, applied before
            # the step and recorded at this tick: a replay re-applies a recorded command
            # before the tick it names, so the run and its replay stay bit-exact
            try:
                tel.poll(self)
            except Exception as exc:    # the outputs never stop the control loop
                self._on_output_error(exc)
        if self._requests:
            self._apply(self._requests.popleft())
        mon.begin_tick()
        try:
            io = self.io
            io.read(now_ns, tick)
            mon.end_receive()
            if mon.fresh:
                self.good_ticks += 1
            elif not mon.sensor_seen:
                self.good_ticks = 0
            if mon.sensor_seen:
                rt = self.rt
                pv = self.road_preview
                start = -1
                if pv is not None:
                    start = self.preview_stream.window_start()  # type: ignore[union-attr]
                    if (start >= 0) is not self.preview_live:
                        self._on_preview_change(start >= 0, now_ns, tick)
                if start >= 0:
                    # the preview's check and the step in one compiled call
                    force_ref = rt.step_previewed(
                        pv, io.rattlespace_m, io.accel_mps2, io.force_meas_n,
                        self.preview_stream.ring, start)  # type: ignore[union-attr]
                    if rt.preview_called:
                        self.preview_calls += 1
                else:
                    force_ref = rt.step(io.rattlespace_m, io.accel_mps2, io.force_meas_n)
                flags = rt.flag_bits
                if (flags ^ self.bank_flags) & _DEGRADED:
                    self._on_degraded_change(flags, now_ns, tick)
                if (flags ^ self.bank_flags) & _STOP_BITS:
                    self._on_stop_contact_change(flags, now_ns, tick)
                if (flags ^ self.bank_flags) & _RIDE_HEIGHT:
                    self._on_ride_height_change(flags, now_ns, tick)
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
            if lc.valve_enabled and self.excitation is not None \
                    and self.excitation_state == "playing":
                force_ref = self._excite(now_ns, tick)    # may disarm at its end
            if lc.valve_enabled:
                spool = self.pi.step(force_ref, io.force_meas_n, io.rattlespace_m)
                mon.output(spool)
                if mon.code is not _NONE:
                    self._latch(mon.code, mon.detail, now_ns)
            self.force_ref_n = force_ref
            self._set_valve_command(spool, force_ref)
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
            rec = self._recorder
            tel = self.telemetry
            feed = tel is not None and tick % self.telemetry_every == 0
            if rec is not None:
                self.io.record_frames()
            if rec is not None or feed:
                record = self._tick_record(now_ns)
                if rec is not None:
                    rec.tick_packed(record)
                if feed:
                    tel.offer_packed(record)  # type: ignore[union-attr]
            else:
                self._last_wake_ns = now_ns
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
        self._set_valve_command(0.0, 0.0)
        try:
            self._send_valve(now_ns, tick)
        except Exception:
            log.exception("could not send the safe valve command")

    def _set_valve_command(self, spool: float, force_ref_n: float) -> None:
        """This tick's valve command: ``spool`` and ``force_ref_n`` with the valve enabled
        when the lifecycle enables it (ACTIVE), else the safe command -- valve disabled,
        spool centred, no force reference -- whatever was asked (the one place the safe
        output is written)."""
        if self.lifecycle.valve_enabled:
            self.enable, self.spool_cmd, self.cmd_force_ref_n = 1, spool, force_ref_n
        else:
            self.enable, self.spool_cmd, self.cmd_force_ref_n = 0, 0.0, 0.0

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

    @property
    def stop_degraded(self) -> bool:
        """The stop-contact monitor has the bank on its travel-conservative law."""
        return bool(self.bank_flags & _STOP_DEGRADED)

    def _on_stop_contact_change(self, flags: int, now_ns: int, tick: int) -> None:
        """A bump-stop contact episode began or ended, or the stop-contact monitor degraded
        or re-armed (controller/stop_contact.py; not faults): count, log (degrade / re-arm,
        at most every 1000th) and record a note with the contact time in the window."""
        changed = flags ^ self.bank_flags
        contact_s = float(self.rt.stop_contact_s)
        if changed & _STOP_CONTACT:
            if flags & _STOP_CONTACT:
                self.stop_contact_episodes += 1
                self._episode_start_tick = tick
            elif self._episode_start_tick >= 0:
                self._record_event(now_ns, tick, "note", {
                    "stop_contact": "episode", "episodes": self.stop_contact_episodes,
                    "start_tick": self._episode_start_tick,
                    "contact_s_in_window": contact_s})
                self._episode_start_tick = -1
        if changed & _STOP_DEGRADED:
            degraded = bool(flags & _STOP_DEGRADED)
            if degraded:
                self.stop_degradations += 1
            if self.stop_degradations % 1000 == 1 or not degraded:
                log.warning("stop contact %s (%.3f s in the window; %d degradations so far)",
                            "over budget: travel-conservative law" if degraded
                            else "re-armed", contact_s, self.stop_degradations)
            self._record_event(now_ns, tick, "note", {
                "stop_contact": "degraded" if degraded else "re-armed",
                "contact_s_in_window": contact_s,
                "stop_degradations": self.stop_degradations})

    @property
    def off_centre(self) -> bool:
        """The ride-height monitor finds the body off the stops' centre."""
        return bool(self.bank_flags & _RIDE_HEIGHT)

    def _on_ride_height_change(self, flags: int, now_ns: int, tick: int) -> None:
        """The ride-height monitor found the body off the stops' centre or centred again
        (controller/ride_height.py; not a fault, the law is unchanged): count, log (at
        most every 1000th episode) and record a note with the ride height and the travel
        left on the side the body sits toward."""
        off = bool(flags & _RIDE_HEIGHT)
        if off:
            self.off_centre_episodes += 1
        height_m = float(self.rt.ride_height_m)
        side = "compression" if height_m > 0.0 else "rebound"
        left_m = self.cfg.vehicle.rattlespace_travel_m - abs(height_m)
        if self.off_centre_episodes % 1000 == 1 or not off:
            if off:
                log.warning("ride height off centre: the body sits %.1f mm toward the %s "
                            "stop, %.1f mm of travel left on that side (ballast or preload "
                            "changed? docs/design.md §9.9)", abs(height_m) * 1e3, side,
                            left_m * 1e3)
            else:
                log.warning("ride height centred again (%.1f mm from the stops' centre)",
                            abs(height_m) * 1e3)
        self._record_event(now_ns, tick, "note", {
            "ride_height": "off centre" if off else "centred",
            "ride_height_m": height_m, "side": side, "travel_left_m": left_m,
            "off_centre_episodes": self.off_centre_episodes})

    def _on_preview_change(self, live: bool, now_ns: int, tick: int) -> None:
        """The road preview became live or was lost (not a fault: without it the travel
        schedule runs on the LVDT reading with design.schedule_start_m / schedule_full_m,
        the governed comfort set on its net alone): switch the schedule's thresholds,
        log and record a note that says why.  A law that takes no preview (the travel
        set alone) only logs it at INFO."""
        self.preview_live = live
        self.rt.use_preview_schedule(live)
        why = self.preview_stream.why_not_live()    # type: ignore[union-attr]
        if not self.rt.takes_road_preview:
            log.info("road preview %s; weight set %d does not take it",
                     "live" if live else f"not live ({why})", self.weight_set)
        elif live:
            log.info("road preview live: the schedule calls the travel law ahead of a "
                     "predicted excursion")
        else:
            log.warning("road preview not live (%s): the law runs on the LVDT reading "
                        "alone", why)
        self._record_event(now_ns, tick, "note", {
            "road_preview": "live" if live else "lost", "why": why,
            "preview_calls": self.preview_calls})

    def _latch(self, code: FaultCode, detail: int, now_ns: int, message: str = "") -> None:
        """Latch FAULT (if not already) and send the FaultReport now."""
        lc = self.lifecycle
        if lc.state is _FAULT or lc.state is _STOPPING:
            return
        if not message:
            message = self._describe(code, detail)
        host_lateness: dict[str, object] | None = None
        try:        # the attribution never stands in the way of the latch
            cause = assess(code, detail, self.tick_count, now_ns, self.timing,
                           stale_ticks=self.monitor.stale_ticks, peer=self.peer_lateness,
                           watchdog_ns=self.peer_watchdog_ns)
            host_lateness = cause.as_dict()
            if cause.attributed:
                message = f"{message} ({cause.phrase()})"
        except Exception:
            log.exception("host-lateness attribution failed")
        lc.fault(code, self.tick_count, now_ns, detail, message, host_lateness)
        self.pi.reset()
        self._send_fault_report(now_ns, self.tick_count)

    def _describe(self, code: FaultCode, detail: int) -> str:
        """A human-readable fault message (only when a fault latches)."""
        if code is FaultCode.EXCEPTION:
            return self.last_exception or "exception"
        return (f"detail {detail}; sensors rs={self.rattlespace_m:.6g} m "
                f"F={self.force_meas_n:.6g} N a={self.accel_mps2:.6g} m/s2, "
                f"age {self.monitor.sensor_age_ticks} ticks, flags {self.bank_flags}")

    def _send_valve(self, now_ns: int, tick: int) -> None:
        if not self.io.write_valve(now_ns, tick, self.enable, int(self.lifecycle.state),
                                   self.spool_cmd, self.cmd_force_ref_n) and self.enable:
            # the command did not go out: the fault latches now, the next tick is safe
            self._latch(self.monitor.code or FaultCode.BUS_ERROR, DETAIL_SEND, now_ns)

    def _send_fault_report(self, now_ns: int, tick: int) -> None:
        lc = self.lifecycle
        self.io.write_fault_report(now_ns, tick, int(lc.state), int(lc.fault_code),
                                   lc.fault_tick, lc.fault_detail)

    def _heartbeat(self, now_ns: int, tick: int) -> None:
        lc = self.lifecycle
        active_fault = lc.fault_code
        if active_fault is _NONE and self.bank_flags & _DEGRADED:
            active_fault = FaultCode.ESTIMATOR_DEGRADED
        self.io.write_status(now_ns, tick, int(lc.state), int(active_fault),
                             self.timing.overruns, self.blending, self.weight_set,
                             self.lateness_p99_us * 1e-6)
        if lc.state is _FAULT:
            self._send_fault_report(now_ns, tick)

    # ------------------------------------------------------------------ outputs
    def _tick_record(self, now_ns: int) -> bytearray:
        """This tick's record for the recorder and the live view, packed (one
        ``ITEM_TICK`` of :data:`TICK_RECORD_FIELDS`; the packer's buffer, valid until
        the next tick)."""
        wake_prev = self._last_wake_ns
        self._last_wake_ns = now_ns
        rec, tel = self.recorder, self.telemetry
        self.wake_interval_ns = now_ns - wake_prev if wake_prev >= 0 else -1
        self.overrun = self.lateness_ns > self.timing.overrun_threshold_ns
        self.recording_dropped = rec.dropped if rec is not None else 0
        self.telemetry_dropped = tel.dropped if tel is not None else 0
        packer = self._packer
        packer.pack(now_ns, self._record_scalars(self), self._record_arrays(self))
        return packer.buffer

    def status(self) -> dict[str, Any]:
        """Full status (off the hot path: built by the telemetry link's status thread)."""
        lc = self.lifecycle
        ride_height_m = float(self.rt.ride_height_m)
        return {
            "lifecycle": lc.state.name,
            "fault": lc.fault_code.name,
            "fault_tick": lc.fault_tick,
            "fault_detail": lc.fault_detail,
            "fault_message": lc.fault_message,
            "fault_host_lateness": lc.fault_host_lateness,
            "condition": self.monitor.condition.name,
            "estimator_degraded": bool(self.bank_flags & _DEGRADED),
            "estimator_degradations": self.degradations,
            "stop_degraded": self.stop_degraded,
            "stop_degradations": self.stop_degradations,
            "stop_contact_episodes": self.stop_contact_episodes,
            "ride_height_m": ride_height_m if math.isfinite(ride_height_m) else None,
            "off_centre": self.off_centre,
            "off_centre_episodes": self.off_centre_episodes,
            "health": self.health_problem() or "ok",
            "tick": self.tick_count,
            "blending": self.blending,
            "weight_set": self.weight_set,
            "road_preview": ("off" if self.preview_stream is None
                             else "unused" if not self.rt.takes_road_preview
                             else self.preview_stream.why_not_live()),
            "preview_calls": self.preview_calls,
            # ticks in which the preview's stop clamp clipped the force toward a stop
            "preview_clamps": self.rt.preview_clamp_ticks,
            # how far the prediction is trusted now (BankRuntime.preview_trust)
            "preview_trust": ("off" if self.road_preview is None
                              else self.rt.preview_trust(self.road_preview)),
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
            duration_s: float | None = None, pacer: TickPacer | None = None) -> None:
        """Tick at the configured rate until ``stop`` is set, ``max_ticks`` ticks were
        done or ``duration_s`` of the loop's clock has passed (skipped deadlines
        included).

        ``on_tick`` (if given) runs after each tick in the loop thread: keep it cheap.
        Pacing: ``pacer``, by default a :class:`rig.rt.pacing.Pacer` on the loop's clock
        (absolute deadlines, missed ones skipped once a whole period is lost), the same
        rule as the emulated rig's; in lockstep with the emulated rig a
        :class:`rig.rt.lockstep.LockstepPacer` (the loop's clock is then its
        :class:`rig.rt.pacing.SteppedClock`)."""
        clock = self.clock_ns
        period = self.period_ns
        if pacer is None:
            pacer = Pacer(period, start_ns=clock() + period, spin_ns=self.spin_ns,
                          clock=clock)
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
        self._set_valve_command(0.0, 0.0)
        try:
            self._send_valve(now, self.tick_count)
            self.io.write_fault_report(now, self.tick_count, int(_STOPPING),
                                       int(FaultCode.SHUTDOWN), self.tick_count, 0)
            self.lateness_p99_us = self.timing.lateness_p99_us()
            self._heartbeat(now, self.tick_count)
        except Exception:
            log.exception("could not send the shutdown frames")
        self.io.record_frames()
