"""The replay driver: an unmodified :class:`rig.service.loop.ControlLoop` fed a recording.

:func:`replay_recording` drives the loop with the recorded tick times (a virtual
clock: no sleeping), the recorded wake-up lateness and compute time (they feed the
overrun check and the heartbeat's p99), re-applies the recorded operator commands at
their ticks, raises the recorded bus exceptions again (through
:class:`rig.replay.buses.McapReplayBus`) and, if the recording ends with a shutdown,
shuts the loop down the same way.  With the recorded design and configuration the
transmitted frames must equal the recorded ones byte for byte; with another design or
configuration the result compares the two controllers on the same sensor data -- open
loop: the recorded plant did not react to the replayed commands.
:func:`replay_log` replays a candump log on a virtual tick grid.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controller.artifact import Design
from controller.config import RigConfig, config_hash, config_to_toml
from rig.recording.recorder import CONFIG_ATTACHMENT, DESIGN_ATTACHMENT, RunRecorder
from rig.recording.scan import RecordingError
from rig.replay.buses import LOG_SUFFIXES, LogReplayBus, McapReplayBus
from rig.replay.reader import PIPELINE_MIN_BYTES, ReaderProcess, idle_cpu
from rig.replay.recorded import (
    Piece,
    RecordedRun,
    as_piece,
    assemble_run,
    design_from_bytes,
    load_recorded_run,
    recorded_config,
    recorded_design,
)
from rig.replay.result import (
    OPEN_LOOP_NOTE,
    ReplayResult,
    compare_tx,
    max_abs_diff,
    series_comparison,
)
from rig.rt.pacing import SteppedClock
from rig.service.assembly import LoopSettings, build_control_loop
from rig.service.lifecycle import Transition
from rig.service.loop import ControlLoop
from rig.wire.protocol import LifecycleState

__all__ = ["replay_file", "replay_log", "replay_recording"]


class _FaultLog:
    """Every FAULT transition of the loop (``loop.transitions`` keeps the last 256)."""

    def __init__(self, loop: ControlLoop) -> None:
        self.codes: list[str] = []
        self.ticks: list[int] = []
        loop.lifecycle.add_listener(self)

    def __call__(self, tr: Transition) -> None:
        if tr.state is LifecycleState.FAULT:
            self.codes.append(tr.fault_code.name)
            self.ticks.append(tr.tick)


def _open_out(out: str | Path, cfg: RigConfig, design_bytes: bytes | None,
              metadata: Mapping[str, Any], clock_offset_ns: int) -> RunRecorder:
    # blocking: a replay runs faster than real time, so it waits for the writer process
    # instead of dropping
    return RunRecorder(out, cfg.recording, config_toml=config_to_toml(cfg),
                       design_bytes=design_bytes, metadata=metadata, clock="replay",
                       clock_offset_ns=clock_offset_ns, blocking=True)


def _apply_commands(loop: ControlLoop, cmds: Sequence[dict[str, Any]]) -> tuple[int, int]:
    """Re-apply recorded commands; (applied, outcome differs from the recording)."""
    differs = 0
    for ev in cmds:
        d = ev["detail"]
        res = loop.request(str(d.get("command")), d.get("argument"), timeout_s=None)
        if "accepted" in d and bool(d["accepted"]) != res.accepted:
            differs += 1
    return len(cmds), differs


class _Replayer:
    """Feeds pieces of a recording through the loop, tick by tick (module docstring)."""

    def __init__(self, loop: ControlLoop, bus: McapReplayBus, clock: SteppedClock) -> None:
        self.loop = loop
        self.bus = bus
        self.clock = clock
        self.period = loop.period_ns
        self.cmds: dict[int, list[dict[str, Any]]] = {}
        self.stop: dict[str, Any] | None = None
        self.first_tick: int | None = None
        self.next_tick = 0
        self.t_prev = 0
        self.missing = 0
        self.applied = 0
        self.differs = 0
        self.spool: list[float] = []
        self.fref: list[float] = []
        self.enable: list[int] = []

    def _commands(self, cmds: Sequence[dict[str, Any]]) -> None:
        a, d = _apply_commands(self.loop, cmds)
        self.applied += a
        self.differs += d

    def feed(self, piece: Piece) -> None:
        self.bus.extend(piece.rx, piece.bus_faults)
        for ev in piece.events:
            d = ev.get("detail")
            if ev.get("kind") == "command" and isinstance(d, dict):
                self.cmds.setdefault(int(ev["tick"]), []).append(ev)
            elif ev.get("kind") in ("lifecycle", "fault") and isinstance(d, dict) \
                    and d.get("to") == LifecycleState.STOPPING.name:
                self.stop = ev
        loop, clock, advance, cmds = self.loop, self.clock, self.bus.advance, self.cmds
        tick_fn = loop.tick
        put_spool, put_fref, put_enable = self.spool.append, self.fref.append, \
            self.enable.append
        period = self.period
        for k, t, late, comp in zip(piece.tick.tolist(), piece.t_ns.tolist(),
                                    piece.lateness_ns.tolist(), piece.compute_ns.tolist(),
                                    strict=True):
            if self.first_tick is None:
                self.first_tick = self.next_tick = k
                loop.tick_count = k
                self.t_prev = t - period
            elif k < self.next_tick:     # a repeated tick record: nothing to re-run
                continue
            while self.next_tick <= k:
                kk = self.next_tick
                if kk < k:               # record lost (recorder queue full)
                    self.missing += 1
                    t_k, late_k, comp_k = self.t_prev + period, 0, 0
                else:
                    t_k, late_k, comp_k = t, late, comp
                c = cmds.pop(kk, None)
                if c is not None:
                    self._commands(c)
                advance(kk)
                clock.now_ns = t_k + comp_k
                tick_fn(t_k, late_k)
                put_spool(loop.spool_cmd)
                put_fref(loop.force_ref_n)
                put_enable(loop.enable)
                self.t_prev = t_k
                self.next_tick = kk + 1

    def finish(self) -> None:
        """What the loop did after its last recorded tick: commands, shutdown."""
        if self.first_tick is None:
            return
        self.bus.advance(self.next_tick)
        later = sorted(k for k in self.cmds if k >= self.next_tick)
        for k in later:
            self._commands(self.cmds.pop(k))
        if self.stop is not None:
            self.clock.now_ns = int(self.stop["t_ns"])
            self.loop.shutdown(str(self.stop["detail"].get("reason", "shutdown")))


def replay_recording(path: str | Path, *, cfg: RigConfig | None = None,
                     design: Design | None = None, design_bytes: bytes | None = None,
                     out: str | Path | None = None, run: RecordedRun | None = None,
                     reader_process: bool | None = None) -> ReplayResult:
    """Replay an MCAP recording through :class:`rig.service.loop.ControlLoop` (module docstring).

    ``cfg`` / ``design`` default to the recording's attachments; given another, the
    result's ``comparison`` compares the two controllers (open loop).  ``out`` writes
    the replay as a new recording (metadata ``replay_of``, ``open_loop``).  ``run``: an
    already loaded recording.  ``reader_process`` reads the file in a forked process
    while replaying (default: for files of at least :data:`PIPELINE_MIN_BYTES` when a
    CPU is idle)."""
    path = Path(path)
    reader: ReaderProcess | None = None
    if reader_process is None:
        reader_process = (path.is_file() and path.stat().st_size >= PIPELINE_MIN_BYTES
                          and idle_cpu())
    if run is None and reader_process:
        reader = ReaderProcess(path)
    try:
        return _replay(path, cfg, design, design_bytes, out, run, reader)
    finally:
        if reader is not None:
            reader.close()


def _replay(path: Path, cfg: RigConfig | None, design: Design | None,
            design_bytes: bytes | None, out: str | Path | None, run: RecordedRun | None,
            reader: ReaderProcess | None) -> ReplayResult:
    if reader is not None:
        scan, first = reader.head()
        head = RecordedRun(path, scan, *(np.zeros(0, np.int64),) * 4,
                           np.zeros(0), np.zeros(0), np.zeros(0, np.int8), [], [], [], first)
        pieces: Iterable[Piece] = reader
    else:
        head = run if run is not None else load_recorded_run(path)
        pieces = [as_piece(head)]
    rec_cfg_raw = head.scan.attachments.get(CONFIG_ATTACHMENT)
    rec_design_raw = head.scan.attachments.get(DESIGN_ATTACHMENT)
    if cfg is None:
        cfg = recorded_config(head)
    if design is None:
        if design_bytes is not None:
            design = design_from_bytes(design_bytes)
        else:
            design = recorded_design(head)
            design_bytes = rec_design_raw
    same_cfg = rec_cfg_raw is not None and config_hash(cfg) == config_hash(
        recorded_config(head))
    same_design = rec_design_raw is not None and design_bytes == rec_design_raw
    same = same_cfg and same_design
    try:
        settings = LoopSettings.from_metadata(head.metadata)
    except ValueError as exc:
        raise RecordingError(f"{head.path}: {exc}") from None
    if not same_cfg:   # another configuration brings its own weight set
        settings = dataclasses.replace(settings, weight_set=cfg.design.weight_set)
    clock = SteppedClock()
    bus = McapReplayBus([], channel=f"mcap-replay:{head.path.name}")
    recorder: RunRecorder | None = None
    if out is not None:
        offset = int(head.metadata.get("clock_offset_ns", "0") or 0)
        recorder = _open_out(out, cfg, design_bytes, {
            "source": "rig replay", "replay_of": str(head.path),
            "replay_of_run_id": head.metadata.get("run_id", ""),
            "open_loop": not same, "same_controller": same,
            **settings.metadata()}, offset)
    loop = build_control_loop(cfg, design, bus, settings, recorder=recorder, clock_ns=clock)
    faults = _FaultLog(loop)
    rp = _Replayer(loop, bus, clock)
    started = time.perf_counter()
    try:
        for piece in pieces:
            rp.feed(piece)
        rp.finish()
    finally:
        elapsed = time.perf_counter() - started
        bus.shutdown()
        if recorder is not None:
            recorder.close()
    if reader is not None:
        assert reader.scan is not None
        run = assemble_run(path, reader.scan, reader.pieces, head.first_internals)
    else:
        run = head
    if run.tick.size == 0 or rp.first_tick is None:
        raise RecordingError(f"{run.path}: no tick records to replay"
                             + (f" ({run.stopped_at})" if run.stopped_at else ""))
    return _result(run, rp, loop, bus, same, faults, elapsed, recorder, out)


def _result(run: RecordedRun, rp: _Replayer, loop: ControlLoop, bus: McapReplayBus,
            same: bool, faults: _FaultLog, elapsed: float, recorder: RunRecorder | None,
            out: str | Path | None) -> ReplayResult:
    """Compare the replay with the recording."""
    notes: list[str] = []
    if not run.complete:
        notes.append(f"recording incomplete: {run.stopped_at}; replayed what comes "
                     "before (up to the last complete chunk)")
    notes.extend(run.scan.notes)
    if rp.missing:
        notes.append(f"{rp.missing} ticks missing from the recording (dropped): replayed "
                     "with interpolated times and zero lateness")
    first_tick = int(rp.first_tick or 0)
    last_tick = rp.next_tick - 1
    spool = np.asarray(rp.spool, dtype=float)
    fref = np.asarray(rp.fref, dtype=float)
    enable = np.asarray(rp.enable, dtype=np.int8)
    rec_tx, rep_tx = run.tx, bus.sent
    if not run.complete:  # the cut may fall inside a tick: its frames are incomplete
        rec_tx = [f for f in run.tx if f[0] <= last_tick]
        rep_tx = [f for f in bus.sent if f[0] <= last_tick]
        if len(rec_tx) < len(run.tx) or len(rep_tx) < len(bus.sent):
            notes.append("frames sent after the last complete tick record were not "
                         f"compared ({len(run.tx) - len(rec_tx)} recorded, "
                         f"{len(bus.sent) - len(rep_tx)} replayed)")
    compared, mism, first, valves, vspool = compare_tx(rec_tx, rep_tx)
    pos = run.tick - first_tick       # replayed series at the recorded ticks
    period = rp.period
    res = ReplayResult(
        source=str(run.path), kind="mcap", same_controller=same, ticks=spool.size,
        rx_frames_fed=bus.fed, elapsed_s=elapsed,
        recorded_s=(int(run.t_ns[-1]) - int(run.t_ns[0]) + period) * 1e-9,
        complete=run.complete, stopped_at=run.stopped_at,
        tx_frames_recorded=len(rec_tx), tx_frames_replayed=len(rep_tx),
        tx_frames_compared=compared, tx_frames_mismatched=mism, first_mismatch=first,
        valve_frames_compared=valves,
        max_abs_command_diff=max_abs_diff(run.spool_cmd, spool[pos]),
        max_abs_valve_frame_spool_diff=vspool,
        max_abs_force_ref_diff_n=max_abs_diff(run.force_ref_n, fref[pos]),
        commands_reapplied=rp.applied, commands_outcome_differs=rp.differs,
        ticks_missing_in_recording=rp.missing, final_state=loop.lifecycle.state.name,
        faults=faults.codes, fault_ticks=faults.ticks,
        bus_exceptions_recorded=bus.faults_loaded, bus_exceptions_raised=bus.faults_raised,
        out=None if recorder is None else str(recorder.base_path),
        out_error=None if recorder is None else recorder.error,
        notes=notes, tick=np.arange(first_tick, last_tick + 1, dtype=np.int64),
        spool_cmd=spool, force_ref_n=fref, valve_enable=enable)
    if bus.faults_raised != bus.faults_loaded:
        notes.append(f"{bus.faults_loaded - bus.faults_raised} of {bus.faults_loaded} "
                     "recorded bus exceptions were not raised again (the replayed loop "
                     "did not receive / send there)")
    if recorder is not None and recorder.error:
        notes.append(f"writing {out}: {recorder.error}")
    if not same:
        res.comparison = series_comparison(run, spool[pos], fref[pos], enable[pos],
                                           faults.codes)
        notes.append(OPEN_LOOP_NOTE)
    return res


def replay_log(path: str | Path, cfg: RigConfig, design: Design, *,
               design_bytes: bytes | None = None, arm_at_s: float | None = None,
               out: str | Path | None = None) -> ReplayResult:
    """Replay a candump ``.log`` / ``.asc`` / ``.blf`` file: ticks on a grid of the
    sample period starting half a period after the first frame (a frame belongs to the
    first tick at or after its timestamp), decoded with the project's DBC codec.  A log
    carries no commands: the controller stays INACTIVE (computing its force reference)
    unless ``arm_at_s`` (seconds after the first frame) arms it."""
    bus = LogReplayBus(path)
    clock = SteppedClock()
    settings = LoopSettings(blending=0, weight_set=cfg.design.weight_set)
    recorder: RunRecorder | None = None
    if out is not None:
        recorder = _open_out(out, cfg, design_bytes, {
            "source": "rig replay", "replay_of": str(path), "open_loop": True,
            **settings.metadata()}, 0)
    loop = build_control_loop(cfg, design, bus, settings, recorder=recorder, clock_ns=clock)
    faults = _FaultLog(loop)
    period = loop.period_ns
    t0_ns = round(bus.start_s * 1e9) + period // 2
    span_ns = round((bus.end_s - bus.start_s) * 1e9)
    n = max(0, span_ns - period // 2 + period - 1) // period + 1   # last frame's tick + 1
    arm_tick = None if arm_at_s is None else round(arm_at_s * 1e9 / period)
    spool, fref = np.empty(n), np.empty(n)
    enable = np.empty(n, dtype=np.int8)
    notes = [OPEN_LOOP_NOTE]
    started = time.perf_counter()
    try:
        for k in range(n):
            if k == arm_tick:
                res = loop.request("arm", timeout_s=None)
                if not res.accepted:
                    notes.append(f"arm at tick {k} refused: {res.message}")
            t = t0_ns + k * period
            bus.advance_time(t * 1e-9)
            clock.now_ns = t
            loop.tick(t, 0)
            spool[k] = loop.spool_cmd
            fref[k] = loop.force_ref_n
            enable[k] = loop.enable
    finally:
        elapsed = time.perf_counter() - started
        bus.shutdown()
        if recorder is not None:
            recorder.close()
    if bus.filtered:
        notes.append(f"{bus.filtered} frames not for the controller (receive filters) "
                     "were skipped")
    if arm_tick is not None and arm_tick >= n:
        notes.append(f"not armed: arm_at_s = {arm_at_s:g} s is after the log's last tick "
                     f"({(n - 1) * period * 1e-9:g} s)")
    return ReplayResult(
        source=str(path), kind="log", same_controller=False, ticks=n,
        rx_frames_fed=bus.fed, elapsed_s=elapsed, recorded_s=n * period * 1e-9,
        tx_frames_replayed=len(bus.sent), final_state=loop.lifecycle.state.name,
        faults=faults.codes, fault_ticks=faults.ticks,
        out=None if recorder is None else str(recorder.base_path),
        out_error=None if recorder is None else recorder.error,
        notes=notes, tick=np.arange(n, dtype=np.int64), spool_cmd=spool, force_ref_n=fref,
        valve_enable=enable)


def replay_file(path: str | Path, *, cfg: RigConfig | None = None,
                design: Design | None = None, design_bytes: bytes | None = None,
                out: str | Path | None = None, arm_at_s: float | None = None
                ) -> ReplayResult:
    """Replay an ``.mcap`` recording or a python-can log file (by suffix)."""
    p = Path(path)
    if p.suffix.lower() in LOG_SUFFIXES:
        if cfg is None:
            raise RecordingError(f"{p}: a log file carries no configuration")
        if design is None:
            raise RecordingError(f"{p}: a log file carries no design")
        return replay_log(p, cfg, design, design_bytes=design_bytes, arm_at_s=arm_at_s,
                          out=out)
    return replay_recording(p, cfg=cfg, design=design, design_bytes=design_bytes, out=out)

