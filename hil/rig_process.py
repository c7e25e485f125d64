"""The emulated rig (:class:`hil.node.RigNode`) in a process of its own.

On the bench the emulated rig (``rig hil``) and the controller (``rig run``) are separate
processes on a vcan/can interface; in ``rig demo``, the loop benchmark and the tests they
are separate processes too, on one :mod:`rig.bus.socketpair` wire, so neither shares a
GIL, a garbage collector or a scheduler class with the other.  :class:`RigProcess` is the
controller side's handle; :func:`main` (``python -m hil.rig_process``, never run by hand)
is the rig side.

Life of the rig process:

1. it reads its set-up (one JSON line on stdin: configuration TOML, road, seed, drive
   watchdog, real-time request, trace size) and the two file descriptors it inherited
   (its end of the wire, the shared trace);
2. builds the road, the plant and the sensors, runs three ticks of a throw-away node on
   a private bus (numba and first-call costs, so that no slow tick reaches the drive
   watchdog), applies its own real-time set-up (:mod:`rig.rt.realtime`) and reports
   ``ready`` on stdout;
3. ticks from the time given by ``start <t_ns>`` (``time.monotonic_ns``, a clock shared
   by all processes) on absolute deadlines until ``stop`` or the end of stdin (the
   controller process ended), then reports ``final`` with its counters.  In lockstep
   (:attr:`RigProcessOptions.lockstep`, :mod:`rig.rt.lockstep`) it ticks instead when
   the control loop hands it the turn, from tick 0, until the loop closes the turn
   channel (or its process ended).

SIGINT / SIGTERM are ignored: the controller process decides when the rig stops (it
sends its safe valve command and its shutdown report first), and a terminal's Ctrl-C
reaches the controller only.

True plant signals (what ideal instruments would read: acceleration, tire force,
hydraulic power ...) are written every tick into a shared memory block
(:class:`RigTrace`, a ``memfd`` both processes map), which the controller side reads
live (``rig demo``'s progress line) and at the end (its summary).  The rig writes a
tick's values before it publishes the new count; on the controller side read
:attr:`RigTrace.count` first, then at most that many values.
"""

from __future__ import annotations

import contextlib
import json
import logging
import mmap
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig, config_to_toml
from hil.node import DEFAULT_WATCHDOG_S, RigNode
from rig.rt.lockstep import LockstepLink
from rig.rt.realtime import RealtimeRequest
from rig.strict_json import json_lines

__all__ = ["TRACE_FIELDS", "RigProcess", "RigProcessError", "RigProcessOptions", "RigTrace",
           "main"]

log = logging.getLogger(__name__)

#: true plant signals written per rig tick (SI units; flags as 0.0 / 1.0)
TRACE_FIELDS = ("accel_mps2", "rattlespace_m", "tire_force_n", "force_n",
                "hydraulic_power_w", "off_ground_s", "bump_stop_s", "bypass_open",
                "watchdog_tripped", "spool_applied", "wake_s", "wake_late_s")
_HEADER_BYTES = 64      # int64 count, int64 capacity, int64 number of fields, padding


class RigProcessError(RuntimeError):
    """The rig process could not be started or set up (the message says why)."""


@dataclass(frozen=True)
class RigProcessOptions:
    """What the emulated rig runs with (the configuration comes separately)."""

    road: str = "rough-course"          # hil.sim.roads.make_road name (or csv:PATH)
    speed_mps: float = 11.176
    road_s: float = 60.0                # road generated; longer runs replay it cyclically
    seed: int | None = None             # road and sensor noise; None = cfg.sensors.seed
    watchdog_s: float = DEFAULT_WATCHDOG_S   # the drive's command watchdog
    trace_ticks: int = 0                # ticks of true plant signals kept (0 = none)
    #: the rig process's own real-time set-up (None = none, and a real-time policy
    #: inherited from the controller process is dropped)
    realtime: RealtimeRequest | None = field(default_factory=RealtimeRequest)
    start_timeout_s: float = 120.0      # for the set-up (imports, numba, road)
    #: tick in turns with the control loop (rig.rt.lockstep) instead of in real time;
    #: RigProcess then needs the rig's end of the turn channel
    lockstep: bool = False


# ---------------------------------------------------------------------------- shared trace


class RigTrace:
    """True plant signals of every rig tick in shared memory (see the module docstring).

    ``arrays[name][:count]`` are valid (``name`` in :data:`TRACE_FIELDS`); ticks beyond
    ``capacity`` are not kept (``count`` stops there)."""

    def __init__(self, fd: int, capacity: int, *, create: bool) -> None:
        self.capacity = int(capacity)
        self._closed_count: int | None = None
        size = _HEADER_BYTES + 8 * len(TRACE_FIELDS) * max(self.capacity, 1)
        if create:
            os.ftruncate(fd, size)
        self._map = mmap.mmap(fd, size)
        self._header = np.frombuffer(self._map, np.int64, 3)
        data = np.frombuffer(self._map, np.float64, len(TRACE_FIELDS) * max(self.capacity, 1),
                             _HEADER_BYTES).reshape(len(TRACE_FIELDS), -1)
        self.arrays: dict[str, NDArray[np.float64]] = {
            name: data[i, :self.capacity] for i, name in enumerate(TRACE_FIELDS)}
        if create:
            self._header[:] = (0, self.capacity, len(TRACE_FIELDS))

    @property
    def count(self) -> int:
        """Ticks written so far (at most ``capacity``; after :meth:`close`, the count
        at the time)."""
        if self._closed_count is not None:
            return self._closed_count
        return int(self._header[0])

    def publish(self, count: int) -> None:
        """Rig side: ticks ``< count`` are written."""
        self._header[0] = count

    def lateness(self, now_ns: int, window_ticks: int, *, period_ns: int) -> tuple[int, int]:
        """How late the rig was (:class:`rig.service.host_lateness.PeerLateness`, read by
        the loop when a SENSOR_STALE latches): ``(late_ns, rig_tick)``, the worst wake-up
        lateness of its last ``window_ticks`` + 2 ticks, or the stall it is in now (the
        time since its last tick woke beyond one ``period_ns``; ``now_ns`` on the same
        monotonic clock), whichever is larger.  Real time only (lockstep traces 0)."""
        n = self.count
        if n == 0:
            return 0, -1
        lo = max(0, n - int(window_ticks) - 2)
        late = self.arrays["wake_late_s"][lo:n]
        i = int(np.argmax(late))
        worst, tick = round(float(late[i]) * 1e9), lo + i
        last_wake_s = float(self.arrays["wake_s"][n - 1])
        if last_wake_s > 0.0:
            stall = now_ns - round(last_wake_s * 1e9) - period_ns
            if stall > worst:
                worst, tick = stall, n
        return worst, tick

    def copy(self) -> dict[str, NDArray[np.float64]]:
        """Plain arrays of the ticks written so far (independent of the shared block)."""
        n = self.count
        return {name: a[:n].copy() for name, a in self.arrays.items()}

    def close(self) -> None:
        """Unmap (views handed out before keep it mapped until they are gone)."""
        if self._closed_count is not None:
            return
        self._closed_count = self.count
        self.arrays = {}
        del self._header
        with contextlib.suppress(BufferError):
            self._map.close()


# ---------------------------------------------------------------------------- controller side


class RigProcess:
    """Start the emulated rig as ``python -m hil.rig_process`` on ``wire_end`` (one end of
    :func:`rig.bus.socketpair.socketpair_wire`; handed over and closed here) and, in
    lockstep, ``turn_end`` (the rig's end of :func:`rig.rt.lockstep.lockstep_pair`,
    handed over and closed here too).

    Construction returns at once (the rig sets itself up in parallel, e.g. while the
    controller designs its bank); :meth:`wait_ready` waits for it, :meth:`start_at`
    starts its ticks, :meth:`stop` ends it and returns its counters."""

    def __init__(self, cfg: RigConfig, options: RigProcessOptions,
                 wire_end: socket.socket, turn_end: socket.socket | None = None) -> None:
        if options.lockstep != (turn_end is not None):
            raise ValueError("a lockstep rig process needs the turn channel (and only it)")
        self.cfg = cfg
        self.options = options
        self.ready_info: dict[str, Any] = {}
        self.final_info: dict[str, Any] = {}
        self.error: str | None = None
        self._built = threading.Event()
        self._ready = threading.Event()
        self._final = threading.Event()
        self._stopped = False
        self._stop_sent = False
        trace_fd = os.memfd_create("rig-trace", os.MFD_CLOEXEC)
        try:
            self.trace = RigTrace(trace_fd, options.trace_ticks, create=True)
            bus_fd = wire_end.fileno()
            turn_fd = -1 if turn_end is None else turn_end.fileno()
            setup = {
                "config_toml": config_to_toml(cfg), "bus_fd": bus_fd, "trace_fd": trace_fd,
                "trace_ticks": options.trace_ticks, "road": options.road,
                "speed_mps": options.speed_mps, "road_s": options.road_s,
                "seed": cfg.sensors.seed if options.seed is None else options.seed,
                "watchdog_s": options.watchdog_s,
                "realtime": None if options.realtime is None else asdict(options.realtime),
                "turn_fd": turn_fd,
            }
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "hil.rig_process"], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                pass_fds=(bus_fd, trace_fd) if turn_end is None else (bus_fd, trace_fd, turn_fd),
                # where `-m hil.rig_process` finds this very copy of the package
                cwd=Path(__file__).resolve().parents[1], start_new_session=True)
        finally:
            os.close(trace_fd)           # the mapping and the child keep the block
            wire_end.close()             # the child has its own copy of this end
            if turn_end is not None:     # ... and of this one: its death ends our waits
                turn_end.close()
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._stdin = self._proc.stdin
        self._status = threading.Thread(target=self._read_status, args=(self._proc.stdout,),
                                        name="rig-process-status", daemon=True)
        self._status.start()
        try:
            self._send(json.dumps(setup))
        except OSError as exc:          # it died at once; its status says why
            self.error = self.error or f"rig process: {exc}"

    @property
    def pid(self) -> int:
        return self._proc.pid

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def _send(self, line: str) -> None:
        self._stdin.write(line.encode() + b"\n")
        self._stdin.flush()

    def _read_status(self, out: IO[bytes]) -> None:
        for st in json_lines(out):
            ev = st.get("event")
            if ev == "built":
                self._built.set()
            elif ev == "ready":
                self.ready_info = st
                self._ready.set()
            elif ev == "final":
                self.final_info = st
                self._final.set()
            elif ev == "error":
                self.error = str(st.get("error"))
        if self.error is None and not self._final.is_set():
            self.error = f"rig process ended unexpectedly (exit status {self._proc.wait()})"
        self._built.set()
        self._ready.set()
        self._final.set()

    def _wait(self, event: threading.Event, what: str, timeout_s: float | None,
              stop_event: threading.Event | None) -> bool:
        timeout = self.options.start_timeout_s if timeout_s is None else timeout_s
        end = time.monotonic() + timeout
        while not event.wait(0.05):
            if stop_event is not None and stop_event.is_set():
                return False
            if time.monotonic() > end:
                raise RigProcessError(f"the emulated rig did not {what} within {timeout:g} s")
        if self.error is not None:
            raise RigProcessError(self.error)
        return True

    def wait_built(self, timeout_s: float | None = None,
                   stop_event: threading.Event | None = None) -> bool:
        """Wait until the rig has read its configuration and built its road (its errors
        come fast, before its numba warm-up).  False if ``stop_event`` was set first;
        RigProcessError if it failed (the message is the rig's) or took too long."""
        return self._wait(self._built, "build its road", timeout_s, stop_event)

    def wait_ready(self, timeout_s: float | None = None,
                   stop_event: threading.Event | None = None) -> dict[str, Any]:
        """Wait until the rig is set up; its ``ready`` report (``realtime``: what its
        real-time set-up got), or {} if ``stop_event`` was set first.  RigProcessError
        if it failed or took too long."""
        if not self._wait(self._ready, "start", timeout_s, stop_event):
            return {}
        if not self.ready_info:
            raise RigProcessError("the emulated rig ended before it was ready")
        return self.ready_info

    def start_at(self, t_ns: int) -> None:
        """Tick k of the rig starts at ``t_ns + k period`` (``time.monotonic_ns``).
        One short pipe write: cheap enough for the control loop's thread."""
        try:
            self._send(f"start {int(t_ns)}")
        except OSError as exc:
            self.error = self.error or f"rig process: {exc}"

    def request_stop(self) -> None:
        """Ask the rig to stop after its current tick; does not wait (loop thread)."""
        if not self._stop_sent:
            self._stop_sent = True
            with contextlib.suppress(OSError, ValueError):
                self._send("stop")

    def stop(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Stop the rig (idempotent); its final counters (:class:`hil.node.NodeStats`
        as a dict, empty if it never got that far)."""
        if not self._stopped:
            self._stopped = True
            self.request_stop()
            with contextlib.suppress(OSError, ValueError):
                self._stdin.close()
            try:
                self._proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.error = self.error or f"rig process did not stop within {timeout_s} s"
                self._proc.kill()            # our own child, by its Popen handle
                self._proc.wait(5.0)
            self._status.join(5.0)
        return dict(self.final_info.get("stats", {}))

    def close(self) -> None:
        self.stop()
        self.trace.close()


# ---------------------------------------------------------------------------- rig side


class _Status:
    def __init__(self, out: IO[str]) -> None:
        self._out = out
        self._lock = threading.Lock()

    def send(self, event: str, **fields: Any) -> None:
        with self._lock, contextlib.suppress(OSError, ValueError):
            self._out.write(json.dumps({"event": event, **fields}, default=str) + "\n")
            self._out.flush()


def _traced_node(trace: RigTrace) -> type[RigNode]:
    """A RigNode class that also writes the true plant signals of each tick to ``trace``."""
    a = trace.arrays
    accel, rattle, tire, force, power, off, bump, bypass, wd, spool, wake, late = (
        a[name] for name in TRACE_FIELDS)
    capacity = trace.capacity

    class TracedRigNode(RigNode):
        def tick(self) -> None:
            super().tick()
            i = self.tick_count - 1
            if i < capacity:
                p = self.plant
                rs, f, acc = p.true_signals()
                accel[i] = acc
                rattle[i] = rs
                force[i] = f
                tire[i] = p.tire_force_n
                power[i] = p.hydraulic_power_w
                off[i] = p.off_ground_time_last_tick_s
                bump[i] = p.bump_stop_time_last_tick_s
                bypass[i] = self.bypass_applied
                wd[i] = self.watchdog_tripped
                spool[i] = self.spool_applied
                wake[i] = self.wake_ns * 1e-9
                late[i] = self.wake_late_ns * 1e-9
                trace.publish(i + 1)

    return TracedRigNode


def _drop_inherited_realtime() -> None:
    if hasattr(os, "sched_setscheduler"):
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _control(lines: IO[bytes], start: threading.Event, stop: threading.Event,
             start_ns: list[int]) -> None:
    """stdin after the set-up: ``start <t_ns>``, ``stop``; the end of stdin = stop."""
    for raw in lines:
        word, _, arg = raw.decode(errors="replace").strip().partition(" ")
        if word == "start" and not start.is_set():
            with contextlib.suppress(ValueError):
                start_ns[0] = int(arg)
            start.set()
        elif word == "stop":
            break
    stop.set()
    start.set()


def _warm_up(cfg: RigConfig, road: Any, seed: int) -> None:
    """Three ticks of a throw-away node on a private virtual bus: compiles and touches
    everything the real node's first ticks would."""
    import uuid

    import can

    bus = can.Bus(interface="virtual", channel=f"rig-warm-{uuid.uuid4().hex}")
    try:
        node = RigNode(bus, cfg, road, seed=seed, record_ticks=1)
        for _ in range(3):
            node.tick()
    finally:
        bus.shutdown()


def _run_lockstep(node: RigNode, link: LockstepLink, stop: threading.Event) -> str | None:
    """Tick when the control loop hands over the turn (``go k``), report each tick done;
    until the loop closes the channel (its shutdown frames are out) or its process ended
    (no wait times out: a dead controller process closes its end).  An error message if
    the turns came out of sequence, else None."""
    error = None
    while not stop.is_set():
        k = link.wait_go()
        if k is None:
            break
        if k != node.tick_count:
            error = f"lockstep out of step: turn {k} at rig tick {node.tick_count}"
            break
        node.tick()
        if not link.done(k):
            break
    link.close()
    return error


def main() -> int:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    status = _Status(sys.stdout)
    stdin = sys.stdin.buffer
    try:
        setup: Mapping[str, Any] = json.loads(stdin.readline())
        import tomllib

        from controller.config import parse_config
        from hil.sim.roads import make_road
        from rig.bus.socketpair import SocketPairBus

        cfg = parse_config(tomllib.loads(setup["config_toml"]))
        seed = int(setup["seed"])
        road = make_road(setup["road"], float(setup["speed_mps"]), float(setup["road_s"]),
                         cfg.sample_time_s, seed=seed)
        trace = RigTrace(int(setup["trace_fd"]), int(setup["trace_ticks"]), create=False)
        status.send("built")
        _warm_up(cfg, road, seed)
        bus = SocketPairBus(fileno=int(setup["bus_fd"]), fd=cfg.can.fd, channel="rig")
        node = _traced_node(trace)(
            bus, cfg, road, watchdog_timeout_s=float(setup["watchdog_s"]), seed=seed,
            record_ticks=1, fd=cfg.can.fd)
    except Exception as exc:  # bad set-up, road, configuration: reported, never raised
        text = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
        status.send("error", error=text)
        return 1
    start, stop = threading.Event(), threading.Event()
    start_ns = [0]
    # before the real-time set-up: a thread started after mlockall() faults in (and locks)
    # its whole stack first
    control = threading.Thread(target=_control, args=(stdin, start, stop, start_ns),
                               name="rig-control", daemon=True)
    control.start()
    rt = setup.get("realtime")
    report: dict[str, Any] = {}
    if rt is None:
        _drop_inherited_realtime()
    else:
        from rig.rt.realtime import apply_realtime

        request: dict[str, Any] = dict(rt)
        request["cpus"] = tuple(request.get("cpus", ()))
        report = apply_realtime(RealtimeRequest(**request)).as_dict()
    status.send("ready", pid=os.getpid(), realtime=report)
    turn_fd = int(setup.get("turn_fd", -1))
    t0 = time.monotonic()
    if turn_fd >= 0:    # lockstep: from tick 0, in turns with the control loop
        lockstep_error = _run_lockstep(node, LockstepLink(fileno=turn_fd, timeout_s=None),
                                       stop)
        if lockstep_error:
            status.send("error", error=lockstep_error)
    else:
        start.wait()
        t0 = time.monotonic()
        if not stop.is_set():
            # a node joining the bus sees only what is sent from now on: commands sent
            # before (the controller runs already) would arm the drive watchdog with old
            # news
            with contextlib.suppress(Exception):
                while bus.recv(0.0) is not None:
                    pass
            node.run(stop, start_ns=start_ns[0] or None)
    with contextlib.suppress(Exception):
        bus.shutdown()
    status.send("final", stats=node.stats.as_dict(), wall_s=time.monotonic() - t0,
                trace_count=trace.count)
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # in lockstep the run ends with the loop's turns, not with stdin: the control thread
    # may still be blocked reading stdin, and a normal interpreter exit then aborts on
    # its buffer's lock ("Fatal Python error: _enter_buffered_busy"); nothing is left
    # to clean up (the final status is out, the bus closed)
    os._exit(code)
