"""The controller service: everything built from the configuration, run until told to stop.

``Service(cfg, ServiceOptions(...))`` loads the design artifact (or designs the bank at
start), opens the bus, the recording (MCAP, its writer process), builds the
:class:`rig.service.loop.ControlLoop` and starts the telemetry process
(:mod:`rig.telemetry_process`) when the Zenoh telemetry or the live Foxglove view is on:
every surface a network client can reach lives there, none in this process (a port
that cannot be served is one line in the log and ``status()["telemetry"]`` /
``status()["foxglove"]``; a lost process is restarted).  :meth:`Service.run`:

1. real-time set-up of the loop thread (best effort, reported: :mod:`rig.rt.realtime`);
2. systemd ``READY=1`` (+ ``STATUS=``), the loop then pings ``WATCHDOG=1`` itself at half
   of ``WATCHDOG_USEC`` (:mod:`rig.rt.sdnotify`);
3. SIGTERM / SIGINT set the stop event (:mod:`rig.rt.stop_signals`; the commands install
   the handlers before the service is built, so that a signal during the design or while
   the bus opens stops it too, see ``stop=``);
4. the loop runs until stopped or ``duration_s``; with ``arm`` it arms as soon as the
   sensors are healthy and the estimator is warm;
5. shutdown: STOPPING, the safe ValveCommand and a SHUTDOWN FaultReport go out, the
   recording is closed completely (summary + footer), exit status 0.  A service closed
   before its loop ran a tick removes its recording: a run leaves a complete recording
   or none.
"""

from __future__ import annotations

import contextlib
import io
import logging
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from controller.config import RigConfig, config_hash, config_to_toml
from controller.modes import blending_of
from rig.operator_commands import loop_argument
from rig.rt.hostcheck import HostCheck, check_host
from rig.rt.pacing import SteppedClock, TickPacer
from rig.rt.realtime import (
    RealtimeReport,
    RealtimeRequest,
    apply_realtime,
    release_cpu_latency,
    restore_gc,
)
from rig.rt.sdnotify import SdNotifier
from rig.rt.stop_signals import StopSignals
from rig.service.assembly import LoopSettings, build_control_loop
from rig.service.loop import ControlLoop

__all__ = ["Service", "ServiceOptions", "design_bytes"]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class ServiceOptions:
    design_path: str | None = None        # artifact (.npz); None = design at start
    interface: str | None = None          # overrides cfg.can.interface
    channel: str | None = None            # overrides cfg.can.channel
    arm: bool = False                     # arm as soon as healthy
    arm_after_s: float = 0.0              # ... but not before this much run time
    duration_s: float | None = None       # None = until SIGTERM / SIGINT
    record: str | None = None             # directory or .mcap path; None = cfg.recording
    recording: bool | None = None         # None = cfg.recording.enabled
    telemetry: bool | None = None         # None = cfg.telemetry.enabled
    controller: str = "fuzzy"             # a bank mode of controller.modes
    weights: int | None = None            # weight set, 1-based; None = cfg.design.weight_set
    realtime: RealtimeRequest | None = field(default_factory=RealtimeRequest)  # None = none
    install_signal_handlers: bool = True  # in run(), unless Service(stop=...) was given
    timing_ring: int = 1 << 16            # per-tick timing samples kept (ring buffer)
    excite: bool = False                  # identification run (cfg.excitation): arm after
                                          # excitation.rest_s, play it, stop after it
    host_check: bool = False              # measure the wake-up latency for
                                          # safety.host_check_s before the first tick


def design_bytes(design: Any) -> bytes:
    """The artifact bytes of ``design`` (for the recording's attachment)."""
    from controller.artifact import save_design

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "design.npz"
        save_design(design, path)
        return path.read_bytes()


class Service:
    """One controller service instance (see the module docstring).

    ``clock``: a settable loop clock (:class:`rig.rt.pacing.SteppedClock`) instead of
    ``time.monotonic_ns``, for a run in lockstep with the emulated rig; :meth:`run` then
    needs the matching ``pacer`` (:class:`rig.rt.lockstep.LockstepPacer`), and the
    recording names the clock ``lockstep`` (its log times: wall time at the start plus
    loop time) and blocks rather than drops (no deadline to protect).

    ``stop``: the command's :class:`rig.rt.stop_signals.StopSignals` (already installed);
    the design is then interruptible, the other set-up steps check it in between
    (:class:`rig.rt.stop_signals.StopRequested` out of the constructor, after closing what
    was opened) and :attr:`stop_event` is its event.  Without it :meth:`run` installs the
    handlers itself (``opts.install_signal_handlers``)."""

    def __init__(self, cfg: RigConfig, opts: ServiceOptions | None = None, *,
                 bus: can.BusABC | None = None, notifier: SdNotifier | None = None,
                 metadata: dict[str, Any] | None = None,
                 stop: StopSignals | None = None,
                 clock: SteppedClock | None = None) -> None:
        self.cfg = cfg
        #: the loop's clock when it is not the machine's (lockstep with the emulated
        #: rig, rig.rt.lockstep); None = time.monotonic_ns
        self.clock = clock
        self.opts = opts = opts or ServiceOptions()
        self._stop = stop
        self.stop_event = stop.event if stop is not None else threading.Event()
        self.realtime_report = RealtimeReport()
        self.host_check: HostCheck | None = None     # opts.host_check's result
        self.exit_reason = ""
        self.recording_discarded = False
        self._own_bus = bus is None
        self.bus: Any = None
        self.notifier: Any = None
        self.recorder: Any = None
        #: the telemetry process (rig.telemetry_process.link.TelemetryLink), or None
        self.telemetry: Any = None
        self.loop: Any = None
        self._closed = False
        #: called once the shutdown frames (safe valve command, SHUTDOWN report) are out
        self.after_shutdown_frames: list[Callable[[], None]] = []
        try:
            self._build(cfg, opts, bus, notifier, metadata)
        except BaseException:
            self._abandon()
            raise

    def _check_stop(self) -> None:
        if self._stop is not None:
            self._stop.check()

    def _build(self, cfg: RigConfig, opts: ServiceOptions, bus: can.BusABC | None,
               notifier: SdNotifier | None, metadata: dict[str, Any] | None) -> None:

        t0 = time.monotonic()
        self._check_stop()
        if opts.design_path:
            from controller.artifact import load_design

            self.design = load_design(opts.design_path, cfg)
            self.design_blob = Path(opts.design_path).read_bytes()
            log.info("design loaded from %s", opts.design_path)
        else:
            from rig.design_cache import design_for

            with (self._stop.interruptible() if self._stop is not None
                  else contextlib.nullcontext()):
                self.design = design_for(cfg)
            self.design_blob = design_bytes(self.design)
            log.info("bank ready at start in %.1f s", time.monotonic() - t0)
        self._check_stop()
        blending = int(blending_of(opts.controller))
        weight_set = cfg.design.weight_set if opts.weights is None else opts.weights
        if cfg.design.preview_horizon_s > 0.0:
            if weight_set == 0:
                log.info("road preview on (%g s ahead): while the rig's RoadPreview frames "
                         "are live the travel schedule calls the travel law ahead of a "
                         "predicted excursion; without them it runs on the LVDT reading "
                         "(schedule_start_m %g m, schedule_full_m %g m; docs/design.md §12)",
                         cfg.design.preview_horizon_s, cfg.design.schedule_start_m,
                         cfg.design.schedule_full_m)
            elif cfg.design.governs(weight_set):
                log.info("road preview on (%g s ahead): while the rig's RoadPreview frames "
                         "are live the travel governor of weight set %d calls the travel "
                         "law ahead of a predicted excursion; with or without them it "
                         "blends to it from governor_start_m %g m (docs/design.md §12)",
                         cfg.design.preview_horizon_s, weight_set,
                         cfg.design.governor_start_m)
            else:
                log.warning("design.preview_horizon_s = %g s is unused: weight set %d is "
                            "a fixed law, only the travel schedule (weight set 0) and the "
                            "governed comfort set take a road preview",
                            cfg.design.preview_horizon_s, weight_set)
        warmup_ticks = round(cfg.safety.arm_warmup_s * cfg.design.sample_rate_hz)
        settings = LoopSettings(blending, weight_set, warmup_ticks, excite=opts.excite)
        if bus is None:
            from rig.bus.core import open_bus

            interface = opts.interface or cfg.can.interface
            # virtual bus: no software receive filters (python-can's recv(timeout=0)
            # returns None at the first filtered frame); the loop ignores unknown IDs.
            role = "controller" if interface == "socketcan" else None
            bus = open_bus(cfg.can, role=role, interface=interface,
                           channel=opts.channel or cfg.can.channel)
        self.bus = bus
        self._check_stop()
        self.notifier = notifier if notifier is not None else SdNotifier.from_environment()
        record_on = cfg.recording.enabled if opts.recording is None else opts.recording
        if opts.record is not None:
            record_on = True
        if record_on:
            from rig.recording.recorder import RunRecorder

            target = opts.record or cfg.recording.directory
            meta = {"source": "rig run", "config_hash": config_hash(cfg),
                    "sample_rate_hz": cfg.design.sample_rate_hz,
                    "models": list(map(str, self.design.model_names)),
                    # what replay needs to build the same loop (rig.service.assembly)
                    **settings.metadata()}
            meta.update(metadata or {})
            # lockstep: no deadline to protect, so the recorder waits for its writer
            # instead of dropping (the run slows down, nothing is lost)
            clock_kw: dict[str, Any] = {} if self.clock is None else {
                "clock": "lockstep", "clock_offset_ns": time.time_ns() - self.clock(),
                "blocking": True}
            self.recorder = RunRecorder(target, cfg.recording, config_toml=config_to_toml(cfg),
                                        design_bytes=self.design_blob, metadata=meta,
                                        **clock_kw)
            self._check_stop()
        self.loop = build_control_loop(cfg, self.design, bus, settings, recorder=self.recorder,
                                       notifier=self.notifier, timing_ring=opts.timing_ring,
                                       clock_ns=self.clock or time.monotonic_ns)
        self.runtime, self.force_loop = self.loop.rt, self.loop.pi
        telemetry_on = cfg.telemetry.enabled if opts.telemetry is None else opts.telemetry
        if telemetry_on or cfg.foxglove.enabled:
            from rig.service.loop import tick_record_layout
            from rig.telemetry_process.link import TelemetryLink

            # the telemetry process: a session or server that cannot start is reported
            # (status, log, systemd STATUS=) and control goes on without it
            self.telemetry = TelemetryLink(
                cfg, tick_record_layout(self.runtime), zenoh=telemetry_on,
                foxglove=cfg.foxglove.enabled, status_provider=self.status,
                clock_offset_ns=getattr(self.recorder, "clock_offset_ns", None),
                on_note=self.notifier.set_note)
            self.loop.telemetry = self.telemetry
            self.loop.telemetry_every = self.telemetry.tick_every
        #: how long :meth:`command_handler` waits for the loop to apply a command [s]
        self.command_timeout_s = 0.05
        self._arm_pending = opts.arm
        arm_after_s = max(opts.arm_after_s, cfg.excitation.rest_s) if opts.excite \
            else opts.arm_after_s
        self._arm_after_ticks = round(arm_after_s * cfg.design.sample_rate_hz)
        #: ticks of passive rest kept after the excitation ended before the run stops
        self._excite_tail_ticks = round(0.5 * cfg.design.sample_rate_hz)
        self._excite_ended_at = -1
        self._check_stop()

    def _abandon(self) -> None:
        """Close what a constructor that failed (or was stopped) had opened; a recording
        started without a tick is removed."""
        self._closed = True
        steps: list[tuple[str, Callable[[], None]]] = []
        if self.telemetry is not None:
            steps.append(("telemetry process", self.telemetry.close))
        if self.recorder is not None:
            steps.append(("recording", self._discard_recording))
        if self.bus is not None and self._own_bus:
            steps.append(("bus", self.bus.shutdown))
        if self.notifier is not None:
            steps.append(("notifier", self.notifier.close))
        for name, close in steps:
            try:
                close()
            except Exception:
                log.exception("closing the %s of a service that did not run", name)

    def _discard_recording(self) -> None:
        """Close the recording and remove its file(s): it holds no tick."""
        rec = self.recorder
        rec.close()
        for path in {*rec.paths, rec.base_path}:
            with contextlib.suppress(FileNotFoundError):
                Path(path).unlink()
        self.recording_discarded = True
        log.info("recording %s removed: the loop ran no tick", rec.base_path)

    # ------------------------------------------------------------------ outside views
    @property
    def recording_path(self) -> Path | None:
        if self.recorder is None or self.recording_discarded:
            return None
        return Path(self.recorder.base_path)

    @property
    def recording_failure(self) -> str | None:
        """Why the recording is incomplete (its writer failed, e.g. a full disk), or None:
        the summary line that replaces ``recording: PATH``."""
        rec = self.recorder
        if rec is None or self.recording_discarded or not rec.error:
            return None
        return (f"recording {rec.base_path} FAILED, it is incomplete: {rec.error} "
                f"({rec.dropped} items lost)")

    @property
    def foxglove(self) -> Any:
        """The live view as the telemetry process reports it (``state``, ``url``,
        ``port``, ``error``, ``status()``), None when it is off."""
        tel = self.telemetry
        return tel.foxglove if tel is not None and tel.foxglove_on else None

    def status(self) -> dict[str, Any]:
        """The service's status (the telemetry link's status thread builds it every
        ``rig.telemetry_process.feed.STATUS_PERIOD_S`` for ``rig/status`` queries, which
        the telemetry process answers; and ``--json``)."""
        s = self.loop.status()
        s["realtime"] = self.realtime_report.as_dict()
        s["recording"] = str(self.recording_path) if self.recording_path else None
        s["telemetry"] = {"state": "off"} if self.telemetry is None \
            else self.telemetry.status()
        s["foxglove"] = self.foxglove_status()
        s["host_check"] = None if self.host_check is None else self.host_check.as_dict()
        return s

    def foxglove_status(self) -> dict[str, Any]:
        """The live view: off, serving (with its URL), failed (with the one-line error)
        or stopped."""
        return {"state": "off"} if self.foxglove is None else self.foxglove.status()

    def command_handler(self, name: str, args: dict[str, Any]) -> str:
        """An operator command from this process (validated JSON arguments,
        ``rig.operator_commands.validate_command``) -> the loop (waits up to
        ``command_timeout_s``); ValueError when refused.  The telemetry process's
        commands take the loop's own path instead (``TelemetryLink.poll``)."""
        res = self.loop.request(name, loop_argument(name, args),
                                timeout_s=self.command_timeout_s)
        if not res.accepted:
            raise ValueError(res.message)
        return res.message

    # ------------------------------------------------------------------ running
    @property
    def ticks_run(self) -> int:
        return 0 if self.loop is None else int(self.loop.tick_count)

    @property
    def stop_signal(self) -> str:
        """The stop signal that ended (or prevented) the run, '' if none came."""
        return self._stop.signal_name if self._stop is not None else ""

    def _on_tick(self, loop: ControlLoop) -> None:
        if self.opts.excite and loop.excitation_state in ("ended", "aborted"):
            # an unattended identification run stops shortly after its excitation
            if self._excite_ended_at < 0:
                self._excite_ended_at = loop.tick_count
                log.info("excitation %s", loop.excitation_state)
            elif loop.tick_count - self._excite_ended_at >= self._excite_tail_ticks:
                self.exit_reason = self.exit_reason or f"excitation {loop.excitation_state}"
                self.stop_event.set()
        if self._arm_pending and loop.tick_count >= self._arm_after_ticks \
                and not loop.health_problem():
            self._arm_pending = False
            res = loop.request("arm", timeout_s=None)
            if not res.accepted:
                log.warning("arm on start refused: %s", res.message)

    def apply_realtime(self, request: RealtimeRequest) -> RealtimeReport:
        """Real-time set-up of the calling thread (the loop's), kept in
        ``realtime_report``.  The telemetry thread stays an ordinary thread: raising it
        alone would put it above Zenoh's own (ordinary) threads that carry its data."""
        self.realtime_report = apply_realtime(request)
        return self.realtime_report

    def _check_host(self) -> None:
        """``opts.host_check``: measure the loop thread's wake-up latency (its real-time
        set-up already applied) for ``safety.host_check_s``; log it, keep it for
        ``status()``; failing with ``safety.host_check_required``, every arm is refused."""
        seconds = self.cfg.safety.host_check_s
        if not self.opts.host_check or seconds <= 0:
            return
        self.host_check = check_host(self.cfg, seconds, applied=self.realtime_report)
        if self.host_check.ok:
            log.info(self.host_check.summary())
            return
        log.warning(self.host_check.summary())
        if self.cfg.safety.host_check_required:
            self.loop.arm_blocker = (f"host check failed (safety.host_check_required): "
                                     f"{'; '.join(self.host_check.verdict.problems)}")
            self.notifier.set_note("host_check", "FAILED: arming refused")
        else:
            self.notifier.set_note("host_check", "FAILED")

    def run(self, on_tick: Callable[[ControlLoop], None] | None = None,
            pacer: TickPacer | None = None) -> int:
        """Run until SIGTERM / SIGINT / ``stop_event`` / ``duration_s``; returns 0.
        Stopped before the first tick, the loop does not start (and the recording is
        removed).  ``pacer``: the loop's pacing (default: real time on its clock)."""
        own_signals = None
        if self._stop is None and self.opts.install_signal_handlers:
            own_signals = self._stop = StopSignals(self.stop_event).install()
        try:
            if self.stop_event.is_set():
                self.exit_reason = self._stop_reason()
                return 0
            if self.opts.realtime is not None:
                self.apply_realtime(self.opts.realtime)
            self._check_host()
            self.notifier.ready(f"{self.loop.lifecycle.state.name}; "
                                f"{self.realtime_report.summary()}"
                                + (f"; {self.host_check.summary()}" if self.host_check
                                   else ""))

            def tick_hook(loop: ControlLoop) -> None:
                self._on_tick(loop)
                if on_tick is not None:
                    on_tick(loop)

            self.loop.run(self.stop_event, on_tick=tick_hook, duration_s=self.opts.duration_s,
                          pacer=pacer)
            if not self.exit_reason:
                self.exit_reason = (self._stop_reason() if self.stop_event.is_set()
                                    else "duration")
        finally:
            self.close()
            if own_signals is not None:
                own_signals.restore()
        return 0

    def _stop_reason(self) -> str:
        return self.stop_signal or "stop requested"

    def close(self) -> None:
        """Shutdown frames, recording closed completely, bus and telemetry closed."""
        if self._closed:
            return
        if self.opts.realtime is not None:
            release_cpu_latency()
            if self.opts.realtime.freeze_gc:
                restore_gc()
        if self.loop.tick_count == 0:       # nothing ran: nothing to shut down or keep
            self.exit_reason = self.exit_reason or self._stop_reason()
            self.notifier.stopping(f"stopping: {self.exit_reason}")
            self._abandon()
            return
        self._closed = True
        self.notifier.stopping(f"stopping: {self.exit_reason or 'close'}")
        self.loop.shutdown(self.exit_reason or "shutdown")
        for callback in self.after_shutdown_frames:
            try:
                callback()
            except Exception:
                log.exception("after-shutdown callback")
        if self.telemetry is not None:
            self.telemetry.close()
        if self.recorder is not None:
            self.recorder.close()
            if self.recorder.error:
                log.error("recording: %s", self.recorder.error)
        if self._own_bus:
            try:
                self.bus.shutdown()
            except (can.CanError, OSError):
                log.exception("bus shutdown")
        self.notifier.close()
        log.info("service stopped (%s): %s", self.exit_reason or "close",
                 _fmt_timing(self.loop.timing.summary()))


def _fmt_timing(s: dict[str, float | int]) -> str:
    out = io.StringIO()
    out.write(f"{s['ticks']} ticks, lateness p50/p99/max {s['lateness_p50_us']:.0f}/"
              f"{s['lateness_p99_us']:.0f}/{s['lateness_max_us']:.0f} us, "
              f"step p99 {s['step_p99_us']:.0f} us, overruns {s['overruns']}, "
              f"skipped {s['skipped']}")
    return out.getvalue()
