"""The replay buses: recorded frames behind python-can's ``can.BusABC``.

* :class:`McapReplayBus` hands the loop the received frames of an MCAP recording
  (:class:`rig.replay.recorded.RecordedRun`), released tick by tick, with their
  recorded flags (error frame, extended ID); it raises the recorded bus exceptions
  again (``recv`` in the recorded tick, ``send`` of the recorded frame ID and attempt,
  :mod:`rig.replay.bus_faults`) and keeps what the loop sends;
* :class:`LogReplayBus` does the same for candump ``.log`` / ``.asc`` / ``.blf`` files
  (python-can's ``can.LogReader``), released by timestamp on a virtual tick grid.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import can

from rig.bus.core import receive_filters
from rig.extras import EXPORT, require
from rig.recording.scan import RecordingError
from rig.replay.bus_faults import BusFault
from rig.replay.recorded import ERROR_FRAME, EXTENDED_ID, RxFrame, TxFrame, load_recorded_run

__all__ = ["LOG_SUFFIXES", "MAX_LOG_SPAN_S", "LogReplayBus", "McapReplayBus",
           "require_log_reader"]

#: candump / Vector / ASAM MDF 4 bus-log formats read through ``can.LogReader`` (.mf4:
#: python-can's MF4Reader, asammdf; what ``rig export --format mf4`` writes)
LOG_SUFFIXES: Final = (".log", ".asc", ".blf", ".mf4")
#: longest time from a log's first to its last frame that replay accepts: the replay
#: keeps three values per tick (6 h at 1 kHz = 21.6 M ticks, ~370 MB, minutes of CPU)
MAX_LOG_SPAN_S: Final = 6 * 3600.0


def require_log_reader(path: str | Path) -> None:
    """Raise :class:`rig.extras.MissingExtraError` when python-can's reader of the log
    ``path`` needs a module that is not installed (.mf4: asammdf, the ``export`` extra;
    without it python-can leaves its MF4 reader out)."""
    if Path(path).suffix.lower() == ".mf4":
        require("asammdf", EXPORT, "replaying an MF4 log")


def _flags(msg: can.Message) -> int:
    return (ERROR_FRAME if msg.is_error_frame else 0) | (EXTENDED_ID if msg.is_extended_id
                                                         else 0)


class _ReplayBus(can.BusABC):
    """Frames released by a key (tick or time); sent frames are kept in :attr:`sent`."""

    def __init__(self, keys: Sequence[float], channel: str, *,
                 can_filters: Sequence[Mapping[str, Any]] | None = None) -> None:
        super().__init__(channel=channel, can_filters=None)
        self._keys = keys
        self._n = len(keys)
        self._i = 0
        self._release: float = -math.inf
        self._rx_filters = can_filters
        self.channel_info = channel
        #: (release key at the time of sending, arbitration id, data, flags) in send order
        self.sent: list[TxFrame] = []
        self.fed = 0       # frames handed to the reader
        self.filtered = 0  # frames skipped by the receive filters

    @property
    def remaining(self) -> int:
        """Frames not yet read."""
        return self._n - self._i

    def release_all(self) -> None:
        """Free-running: every remaining frame is readable now (a plain log player)."""
        self._release = math.inf

    def _message(self, i: int) -> can.Message:
        raise NotImplementedError

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        keys = self._keys
        while self._i < self._n and keys[self._i] <= self._release:
            msg = self._message(self._i)
            self._i += 1
            if self._rx_filters is not None and not self._rx_match(msg):
                self.filtered += 1
                continue
            self.fed += 1
            return msg, True
        return None, True

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next released frame or None -- never waits: in a replay nothing arrives
        while the reader waits (BusABC.recv's timeout bookkeeping is skipped)."""
        return self._recv_internal(timeout)[0]

    def _rx_match(self, msg: can.Message) -> bool:
        filters = self._rx_filters
        if not filters:
            return True
        for f in filters:
            ext = f.get("extended")
            if ext is not None and bool(ext) != msg.is_extended_id:
                continue
            if (msg.arbitration_id ^ f["can_id"]) & f["can_mask"] == 0:
                return True
        return False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        key = self._release
        self.sent.append((int(key) if math.isfinite(key) else -1, msg.arbitration_id,
                          bytes(msg.data), _flags(msg)))


class McapReplayBus(_ReplayBus):
    """The received frames of a recording; :meth:`advance` releases those the loop read
    in ticks up to and including ``tick`` (the frames carry their recorded time and
    flags).  ``bus_faults``: the recorded bus exceptions, raised again -- ``recv`` in
    its tick once the tick's frames are read (the loop stops draining at an exception),
    ``send`` at the recorded attempt of the recorded frame ID in its tick."""

    def __init__(self, frames: Sequence[RxFrame], channel: str = "mcap-replay",
                 bus_faults: Iterable[BusFault] = ()) -> None:
        self._frames: Sequence[RxFrame] = frames
        super().__init__([f[0] for f in frames], channel)
        self._tick = -1
        self._recv_faults: dict[int, BusFault] = {}
        self._send_faults: dict[tuple[int, int], list[BusFault]] = {}
        self._send_attempts: dict[tuple[int, int], int] = {}
        self.faults_loaded = 0   # recorded bus exceptions handed to the bus
        self.faults_raised = 0   # ... raised again
        self._add_faults(bus_faults)

    @classmethod
    def from_file(cls, path: str | Path) -> McapReplayBus:
        run = load_recorded_run(path)
        return cls(run.rx, channel=f"mcap-replay:{Path(path).name}",
                   bus_faults=run.bus_faults)

    def advance(self, tick: int) -> None:
        self._release = tick
        self._tick = tick

    def extend(self, frames: Sequence[RxFrame], bus_faults: Iterable[BusFault] = ()
               ) -> None:
        """More frames and bus exceptions (a reader delivers a recording piece by
        piece)."""
        if not isinstance(self._frames, list):
            self._frames = list(self._frames)
        self._frames.extend(frames)
        assert isinstance(self._keys, list)
        self._keys.extend(f[0] for f in frames)
        self._n = len(self._keys)
        self._add_faults(bus_faults)

    def _add_faults(self, faults: Iterable[BusFault]) -> None:
        for f in faults:
            self.faults_loaded += 1
            if f.where == "recv":
                self._recv_faults.setdefault(f.tick, f)   # the loop stops at the first
            else:
                self._send_faults.setdefault((f.tick, int(f.arbitration_id or 0)),
                                             []).append(f)

    def _message(self, i: int) -> can.Message:
        _, t_ns, fid, data, flags = self._frames[i]
        if flags:
            error, extended = bool(flags & ERROR_FRAME), bool(flags & EXTENDED_ID)
        else:   # a standard data frame (the common case: no test per flag)
            error = extended = False
        return can.Message(timestamp=t_ns * 1e-9, arbitration_id=fid, data=data,
                           is_extended_id=extended, is_error_frame=error, dlc=len(data),
                           is_rx=True, channel=self.channel_info)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next released frame or None -- never waits; raises the exception
        recorded in this tick once its frames are read."""
        msg = self._recv_internal(timeout)[0]
        if msg is None and self._recv_faults:
            fault = self._recv_faults.pop(self._tick, None)
            if fault is not None:
                self.faults_raised += 1
                raise fault.exception()
        return msg

    def release_all(self) -> None:
        super().release_all()
        self._tick = -1

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Keep the frame, or raise the exception recorded for this send."""
        if self._send_faults:
            fault = self._send_fault(msg.arbitration_id)
            if fault is not None:
                self.faults_raised += 1
                raise fault.exception()
        self.sent.append((self._tick, msg.arbitration_id, bytes(msg.data),
                          (ERROR_FRAME if msg.is_error_frame else 0)
                          | (EXTENDED_ID if msg.is_extended_id else 0)))

    def _send_fault(self, arbitration_id: int) -> BusFault | None:
        key = (self._tick, arbitration_id)
        faults = self._send_faults.get(key)
        if faults is None:
            return None
        n = self._send_attempts.get(key, 0)
        self._send_attempts[key] = n + 1
        for j, f in enumerate(faults):
            if f.attempt is None or f.attempt == n:
                del faults[j]
                if not faults:
                    del self._send_faults[key]
                    del self._send_attempts[key]
                return f
        return None


class LogReplayBus(_ReplayBus):
    """Frames of a candump ``.log`` / ``.asc`` / ``.blf`` file (``can.LogReader``);
    :meth:`advance_time` releases those stamped at or before ``t_s``.  By default only
    the frames the controller subscribes to pass (``rig.bus.core.receive_filters``)."""

    def __init__(self, path: str | Path, *, role: str | None = "controller") -> None:
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"{p}: no such log file")
        if p.suffix.lower() not in LOG_SUFFIXES:
            raise RecordingError(f"{p}: unknown log format {p.suffix!r}; replay reads "
                                 f"{', '.join(LOG_SUFFIXES)} and .mcap")
        require_log_reader(p)
        try:
            with can.LogReader(str(p)) as reader:
                msgs = list(reader)
        except Exception as exc:  # each python-can reader fails its own way
            raise RecordingError(f"{p}: not a readable {p.suffix} log "
                                 f"({type(exc).__name__}: {exc})") from exc
        if not msgs:
            raise RecordingError(f"{p}: no CAN frames in the log")
        for i, m in enumerate(msgs):
            if not math.isfinite(m.timestamp):
                raise RecordingError(f"{p}: frame {i + 1} (ID 0x{m.arbitration_id:X}) has the "
                                     f"time {m.timestamp}: every frame needs a finite "
                                     "timestamp [s]")
        msgs.sort(key=lambda m: m.timestamp)   # stable: file order within a timestamp
        span = msgs[-1].timestamp - msgs[0].timestamp
        if span > MAX_LOG_SPAN_S:
            raise RecordingError(f"{p}: the frames span {span:.6g} s ({msgs[0].timestamp:.6g}"
                                 f" to {msgs[-1].timestamp:.6g} s); a replayed log may span "
                                 f"at most {MAX_LOG_SPAN_S:g} s: split it")
        self.messages = msgs
        self.start_s = msgs[0].timestamp
        self.end_s = msgs[-1].timestamp
        super().__init__([m.timestamp for m in msgs], f"log-replay:{p.name}",
                         can_filters=receive_filters(role))

    def advance_time(self, t_s: float) -> None:
        self._release = t_s

    def _message(self, i: int) -> can.Message:
        return self.messages[i]

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((-1, msg.arbitration_id, bytes(msg.data), _flags(msg)))


