"""The emulated rig as a CAN node: plant + sensors + drive watchdog + fault injection.

Every tick (``cfg.design.sample_rate_hz``) :meth:`RigNode.tick`:

1. reads every pending frame (``recv(timeout=0)``); a ValveCommand is *valid* when its
   length, E2E CRC and ranges are good and its rolling counter is new (a repeated
   counter is a stale command: ignored); bad frames are counted, never applied;
2. runs the drive's own watchdog: armed by the first valid command, it trips when no
   valid command arrived for more than ``watchdog_timeout_s`` (default 5 ms) and then
   holds the safe state (bypass open, spool 0 = passive suspension) and flags
   ``WatchdogTripped`` until a valid command with ``Enable = 1`` arrives;
3. advances the :class:`hil.sim.plant.RigPlant` one tick with the last valid command
   (``Enable = 0``, tripped watchdog or no command yet -> bypass open, spool 0);
4. reads the :class:`hil.sim.sensors.SensorSuite` and sends SensorData (rolling counter +
   CRC), and RigStatus every ``sample_rate / status_rate_hz`` ticks, applying the
   :class:`hil.faults.FaultSchedule` windows active at this tick.

What it applied is recorded per tick in :attr:`RigNode.record` (a ring buffer) so tests
can measure fault reactions.  ``run(stop_event, realtime=True)`` paces ticks on absolute
``time.monotonic_ns`` deadlines; ``tick()`` alone steps deterministically (tests).
"""

from __future__ import annotations

import random
import threading
from collections import deque
from dataclasses import asdict, dataclass

import can
import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig
from hil.faults import FaultKind, FaultSchedule, FaultWindow
from hil.sim.plant import RigPlant
from hil.sim.roads import Road
from hil.sim.sensors import SensorSuite
from rig.bus.core import classify_bus_exception, classify_error_frame, make_tx_message
from rig.rt.pacing import Pacer
from rig.wire.dbc_constants import RIG_STATUS_CYCLE_TIME_MS
from rig.wire.protocol import (
    CONTROLLER_STATUS,
    CONTROLLER_STATUS_ID,
    FAULT_REPORT,
    FAULT_REPORT_ID,
    RIG_STATUS,
    RIG_STATUS_ID,
    ROAD_PREVIEW,
    ROAD_PREVIEW_ID,
    SENSOR_DATA,
    SENSOR_DATA_ID,
    VALVE_COMMAND,
    VALVE_COMMAND_ID,
    ControllerStatus,
    CounterMonitor,
    CounterStatus,
    DecodeStatus,
    FaultCode,
    FaultReport,
    ValveCommand,
)

__all__ = ["NodeRecord", "NodeStats", "RigNode"]

DEFAULT_WATCHDOG_S = 0.005
#: a tick that starts later than this after its deadline counts in NodeStats.late_ticks
LATE_TICK_NS = 200_000
#: RigStatus rate: the DBC's GenMsgCycleTime of RigStatus
DEFAULT_STATUS_RATE_HZ = 1000.0 / RIG_STATUS_CYCLE_TIME_MS
_NO_WINDOWS: list[FaultWindow] = []  # never mutated
_NO_KINDS: frozenset[FaultKind] = frozenset()


@dataclass
class NodeStats:
    """Counters of one node run (``rig hil`` prints them)."""

    ticks: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    valve_commands: int = 0  #: valid (applied) ValveCommands
    bad_frames: int = 0  #: bad length / CRC / range
    stale_commands: int = 0  #: ValveCommands with a repeated counter (ignored)
    lost_commands: int = 0  #: ValveCommands missing per the counter
    unknown_frames: int = 0
    watchdog_trips: int = 0
    send_errors: int = 0
    bus_errors: int = 0  #: error frames / receive exceptions
    late_ticks: int = 0  #: realtime: ticks started after their deadline
    resyncs: int = 0  #: realtime: fell > max_lag behind, schedule reset
    max_lateness_s: float = 0.0

    def summary(self) -> str:
        return (f"ticks={self.ticks} sent={self.frames_sent} received={self.frames_received}"
                f" valve_ok={self.valve_commands} bad={self.bad_frames}"
                f" stale={self.stale_commands} lost={self.lost_commands}"
                f" watchdog_trips={self.watchdog_trips} send_errors={self.send_errors}"
                f" late_ticks={self.late_ticks} max_late_ms={1e3 * self.max_lateness_s:.3f}")

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


class NodeRecord:
    """Per-tick record of what the rig applied and sent, in a ring buffer of
    ``capacity`` ticks (oldest overwritten).  :meth:`arrays` returns them in order."""

    FIELDS = ("tick", "spool_applied", "bypass_open", "watchdog_tripped", "command_valid",
              "sensor_sent", "supply_lost", "actuator_force_n", "rattlespace_m",
              "sensor_counter")

    def __init__(self, capacity: int) -> None:
        self.capacity = max(1, int(capacity))
        n = self.capacity
        self.tick = np.zeros(n, np.int64)
        self.spool_applied = np.zeros(n)
        self.bypass_open = np.zeros(n, bool)
        self.watchdog_tripped = np.zeros(n, bool)
        self.command_valid = np.zeros(n, bool)
        self.sensor_sent = np.zeros(n, bool)
        self.supply_lost = np.zeros(n, bool)
        self.actuator_force_n = np.zeros(n)
        self.rattlespace_m = np.zeros(n)
        self.sensor_counter = np.zeros(n, np.int8)
        self.count = 0

    def arrays(self) -> dict[str, NDArray[np.generic]]:
        """Copies of the recorded series, oldest first (``tick`` is the rig tick)."""
        n = min(self.count, self.capacity)
        start = self.count % self.capacity if self.count > self.capacity else 0
        order = (np.arange(n) + start) % self.capacity
        return {name: getattr(self, name)[order].copy() for name in self.FIELDS}


class RigNode:
    """The emulated rig on a CAN bus (see the module docstring).

    ``bus`` is any ``can.BusABC`` (filters for ValveCommand / FaultReport /
    ControllerStatus are the caller's choice: :func:`rig.bus.core.open_bus` with
    ``role="rig"``).  ``road`` is replayed cyclically; ``seed`` (default
    ``cfg.sensors.seed``) seeds the sensor noise, ``faults.seed`` the random faults.
    """

    def __init__(self, bus: can.BusABC, cfg: RigConfig, road: Road,
                 faults: FaultSchedule | None = None, *,
                 watchdog_timeout_s: float = DEFAULT_WATCHDOG_S,
                 status_rate_hz: float = DEFAULT_STATUS_RATE_HZ,
                 seed: int | None = None, plant: RigPlant | None = None,
                 sensors: SensorSuite | None = None, record_ticks: int = 600_000,
                 fd: bool = False) -> None:
        self.bus = bus
        self.cfg = cfg
        self.dt_s = cfg.sample_time_s
        if abs(road.dt_s - self.dt_s) > 1e-12 * self.dt_s:
            raise ValueError(f"road sampled at {road.dt_s} s, rig ticks at {self.dt_s} s")
        if road.n_ticks < 1:
            raise ValueError("road has no samples")
        if not watchdog_timeout_s > 0:
            raise ValueError(f"watchdog_timeout_s must be > 0, got {watchdog_timeout_s}")
        self.road = road
        self.faults = faults or FaultSchedule()
        self.faults.bind(self.dt_s)
        self._rng = random.Random(self.faults.seed)
        self.plant = plant or RigPlant(cfg)
        self.sensors = sensors or SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=self.dt_s)
        self.watchdog_timeout_s = float(watchdog_timeout_s)
        self._wd_ticks = max(1, round(watchdog_timeout_s / self.dt_s))
        self._status_every = max(1, round(cfg.design.sample_rate_hz / status_rate_hz))
        self.stats = NodeStats()
        #: the current tick's wake-up time and lateness [ns, monotonic] in real time (0 in
        #: lockstep and when stepped); ``rig demo`` traces them (host-lateness attribution)
        self.wake_ns = 0
        self.wake_late_ns = 0
        self.record = NodeRecord(record_ticks)
        self.tick_count = 0
        # received state
        self.command = ValveCommand()  # last valid command
        self._rx_cmd = ValveCommand()
        self.controller_status = ControllerStatus()
        self.fault_report = FaultReport()
        self.command_monitor = CounterMonitor()
        self.armed = False
        self.watchdog_tripped = False
        self.last_valid_tick = -1
        self.last_bus_fault = FaultCode.NONE
        # transmit state
        self._sensor_msg = make_tx_message(SENSOR_DATA_ID, fd)
        self._preview_msg = make_tx_message(ROAD_PREVIEW_ID, fd)
        #: RoadPreview lead [ticks] (emulator.road_preview_s; 0: no RoadPreview frames)
        self.preview_lead = round(cfg.emulator.road_preview_s / self.dt_s)
        self._preview_counter = 15
        self._status_msg = make_tx_message(RIG_STATUS_ID, fd)
        self._late_msg = make_tx_message(SENSOR_DATA_ID, fd)
        self._sensor_counter = 15  # first frame carries 0
        self._status_counter = 15
        self._last_values = (0, 0.0, 0.0, 0.0)  # status, rattlespace, force, accel as sent
        self._delayed: deque[tuple[int, int, bytes]] = deque()
        self.bypass_applied = True
        self.spool_applied = 0.0

    # ----------------------------------------------------------------- receive
    def _receive(self) -> None:
        bus = self.bus
        stats = self.stats
        for _ in range(4096):
            try:
                msg = bus.recv(timeout=0.0)
            except (can.CanError, OSError) as exc:
                stats.bus_errors += 1
                self.last_bus_fault = classify_bus_exception(exc)
                return
            if msg is None:
                return
            if msg.is_error_frame:
                stats.bus_errors += 1
                self.last_bus_fault = classify_error_frame(msg)
                continue
            stats.frames_received += 1
            fid = msg.arbitration_id
            if msg.is_extended_id or msg.is_remote_frame:
                stats.unknown_frames += 1
            elif fid == VALVE_COMMAND_ID:
                self._on_valve_command(msg.data)
            elif fid == CONTROLLER_STATUS_ID:
                if CONTROLLER_STATUS.decode(msg.data, self.controller_status) \
                        is not DecodeStatus.OK:
                    stats.bad_frames += 1
            elif fid == FAULT_REPORT_ID:
                if FAULT_REPORT.decode(msg.data, self.fault_report) is not DecodeStatus.OK:
                    stats.bad_frames += 1
            else:
                stats.unknown_frames += 1

    def _on_valve_command(self, data: bytearray) -> None:
        rx = self._rx_cmd
        if VALVE_COMMAND.decode(data, rx) is not DecodeStatus.OK:
            self.stats.bad_frames += 1
            return
        status = self.command_monitor.check(rx.counter)
        if status is CounterStatus.REPEATED:
            self.stats.stale_commands += 1
            return
        if status is CounterStatus.JUMPED:
            self.stats.lost_commands += self.command_monitor.lost
        self.stats.valve_commands += 1
        self._rx_cmd, self.command = self.command, rx
        self.last_valid_tick = self.tick_count
        self.armed = True
        if rx.enable:
            self.watchdog_tripped = False

    # ----------------------------------------------------------------- transmit
    def _send(self, msg: can.Message) -> bool:
        try:
            self.bus.send(msg, 0.0)
        except (can.CanError, OSError) as exc:
            self.stats.send_errors += 1
            self.last_bus_fault = classify_bus_exception(exc)
            return False
        self.stats.frames_sent += 1
        return True

    def _transmit(self, msg: can.Message, frame: str, active: list[FaultWindow],
                  silent: bool) -> bool:
        """Send ``msg`` (already encoded) through the frame-level faults."""
        if silent:
            return False
        for w in active:
            if not w.hits(frame):
                continue
            if w.kind is FaultKind.DROP and self._rng.random() < w.params["probability"]:
                return False
            if w.kind is FaultKind.DELAY:
                self._delayed.append((self.tick_count + int(w.params["ticks"]),
                                      msg.arbitration_id, bytes(msg.data)))
                return False
        return self._send(msg)

    def _release_delayed(self, silent: bool) -> None:
        q = self._delayed
        while q and q[0][0] <= self.tick_count:
            _, fid, data = q.popleft()
            if silent:
                continue
            m = self._late_msg
            m.arbitration_id = fid
            m.data[:] = data
            self._send(m)

    # ----------------------------------------------------------------- one tick
    def tick(self) -> None:
        """One rig tick (receive, watchdog, plant, sensors, transmit).  Never sleeps."""
        k = self.tick_count
        active = self.faults.active(k) if self.faults.windows else _NO_WINDOWS
        kinds: frozenset[FaultKind] | set[FaultKind] = (
            {w.kind for w in active} if active else _NO_KINDS)
        silent = FaultKind.SILENCE in kinds
        self._receive()

        # drive watchdog
        if self.armed and not self.watchdog_tripped and k - self.last_valid_tick > self._wd_ticks:
            self.watchdog_tripped = True
            self.stats.watchdog_trips += 1
        engaged = self.armed and not self.watchdog_tripped and bool(self.command.enable)
        spool = float(self.command.spool_command) if engaged else 0.0
        self.spool_applied = spool
        self.bypass_applied = not engaged
        supply_lost = FaultKind.SUPPLY_LOSS in kinds
        if supply_lost != self.plant.supply_lost:
            self.plant.set_supply_lost(supply_lost)

        i = k % self.road.n_ticks  # replayed cyclically (the plant re-anchors the height)
        self.plant.advance(self.dt_s, spool, self.bypass_applied,
                           float(self.road.height_m[i]), float(self.road.velocity_mps[i]))
        reading = self.sensors.read(self.plant)

        # SensorData
        self._release_delayed(silent)
        if FaultKind.FROZEN_SENSOR in kinds:
            status, rs, force, acc = self._last_values
        else:
            status, rs, force, acc = reading.status, reading.rattlespace_m, reading.force_n, \
                reading.accel_mps2
            for w in active:
                if w.kind is FaultKind.OUT_OF_RANGE:
                    sig, val = w.params["signal"], w.params["value"]
                    if sig in ("rattlespace", "all"):
                        rs = val
                    if sig in ("force", "all"):
                        force = val
                    if sig in ("accel", "all"):
                        acc = val
                elif w.kind is FaultKind.SENSOR_STATUS:
                    status |= int(w.params["bits"])
            self._last_values = (status, rs, force, acc)
        sensor_sent = self._send_frame(self._sensor_msg, "sensor", active, silent,
                                       status, rs, force, acc)

        # RoadPreview: the road velocity played preview_lead ticks after this one
        if self.preview_lead:
            v = float(self.road.velocity_mps[(k + self.preview_lead) % self.road.n_ticks])
            self._send_frame(self._preview_msg, "preview", active, silent, v)

        # RigStatus
        if k % self._status_every == 0:
            self._send_frame(self._status_msg, "status", active, silent)

        rec = self.record
        j = rec.count % rec.capacity
        rec.tick[j] = k
        rec.spool_applied[j] = spool
        rec.bypass_open[j] = self.bypass_applied
        rec.watchdog_tripped[j] = self.watchdog_tripped
        rec.command_valid[j] = self.last_valid_tick == k
        rec.sensor_sent[j] = sensor_sent
        rec.supply_lost[j] = supply_lost
        rec.actuator_force_n[j] = self.plant.actuator_force_n
        rec.rattlespace_m[j] = reading.rattlespace_m
        rec.sensor_counter[j] = self._sensor_counter
        rec.count += 1
        self.tick_count = k + 1
        self.stats.ticks = self.tick_count

    def _send_frame(self, msg: can.Message, frame: str, active: list[FaultWindow],
                    silent: bool, *values: float) -> bool:
        stuck = False
        xor = 0
        for w in active:
            if w.hits(frame):
                if w.kind is FaultKind.STUCK_COUNTER:
                    stuck = True
                elif w.kind is FaultKind.CORRUPT_CRC:
                    xor = int(w.params["xor"])
        if frame == "sensor":
            if not stuck:
                self._sensor_counter = (self._sensor_counter + 1) & 0xF
            s, rs, force, acc = values
            SENSOR_DATA.encode(msg.data, self._sensor_counter, int(s), rs, force, acc)
        elif frame == "preview":
            if not stuck:
                self._preview_counter = (self._preview_counter + 1) & 0xF
            ROAD_PREVIEW.encode(msg.data, self._preview_counter, 0, values[0],
                                self.preview_lead, self._sensor_counter)
        else:
            if not stuck:
                self._status_counter = (self._status_counter + 1) & 0xF
            p = self.plant
            RIG_STATUS.encode(msg.data, self._status_counter, self.bypass_applied,
                              self.watchdog_tripped, not p.supply_lost, p.supply_pressure_pa,
                              p.spool, p.load_pressure_pa)
        if xor:
            msg.data[0] ^= xor
        return self._transmit(msg, frame, active, silent)

    # ----------------------------------------------------------------- running
    def run(self, stop_event: threading.Event, realtime: bool = True,
            duration_s: float | None = None, max_lag_s: float | None = None,
            start_ns: int | None = None) -> NodeStats:
        """Tick until ``stop_event`` is set or ``duration_s`` of rig time has passed.

        Real time: tick k starts at t0 + k dt (absolute deadlines,
        :class:`rig.rt.pacing.Pacer`, the control loop's rule); a tick that starts late is
        counted, and falling more than ``max_lag_s`` behind skips the missed deadlines
        (counted in ``resyncs``; the schedule stays on its grid) instead of bursting
        through them.  Default: half the drive watchdog window, since a burst passes
        rig time without any command being able to arrive and would trip the watchdog.
        ``start_ns`` (``time.monotonic_ns`` clock) sets t0, e.g. half a period after the
        controller's deadlines when both share a process (``rig demo``): the two threads
        then take turns with the GIL instead of waking together; default: now.
        """
        period_ns = round(self.dt_s * 1e9)
        if max_lag_s is None:
            max_lag_s = (self._wd_ticks // 2) * self.dt_s
        end_tick = None if duration_s is None else self.tick_count + round(duration_s / self.dt_s)
        stats = self.stats
        pacer = Pacer(period_ns, start_ns=start_ns, max_lag_ns=round(max_lag_s * 1e9))
        while not stop_event.is_set():
            if end_tick is not None and self.tick_count >= end_tick:
                break
            if realtime:
                now = pacer.wait()
                late = now - pacer.deadline
                self.wake_ns, self.wake_late_ns = now, late
                if late > LATE_TICK_NS:
                    stats.late_ticks += 1
                    stats.max_lateness_s = max(stats.max_lateness_s, late * 1e-9)
            self.tick()
            if realtime and pacer.advance():
                stats.resyncs += 1
        return stats
