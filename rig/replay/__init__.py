"""Replay of recorded runs through the live loop code (``docs/replay.md``).

A replay is one more ``can.BusABC`` behind the project's one bus abstraction, feeding
an unmodified :class:`rig.service.loop.ControlLoop` with a virtual clock.  Modules:

* :mod:`rig.recording.scan` (re-exported here) -- the one MCAP reader of recordings
  (also used by ``rig report`` and ``read_run``): batches of JSON payloads per chunk
  and topic; clear errors for files that are not replayable; truncated / corrupt tails
  read up to the last complete chunk;
* :mod:`rig.replay.recorded` -- decodes the batches into a :class:`RecordedRun` (tick
  times, lateness, outputs, frames with their flags, events, bus exceptions);
* :mod:`rig.replay.bus_faults` -- recorded recv / send exceptions, raised again;
* :mod:`rig.replay.reader` -- the reader process (reads while the loop replays);
* :mod:`rig.replay.buses` -- :class:`McapReplayBus`, :class:`LogReplayBus`;
* :mod:`rig.replay.result` -- :class:`ReplayResult`, the comparison with the recording;
* :mod:`rig.replay.driver` -- :func:`replay_recording`, :func:`replay_log`,
  :func:`replay_file`.
"""

from __future__ import annotations

from rig.recording.scan import RecordingError, ScanResult, scan_recording
from rig.replay.bus_faults import BusFault
from rig.replay.buses import (
    LOG_SUFFIXES,
    MAX_LOG_SPAN_S,
    LogReplayBus,
    McapReplayBus,
    require_log_reader,
)
from rig.replay.driver import replay_file, replay_log, replay_recording
from rig.replay.reader import PIPELINE_MIN_BYTES
from rig.replay.recorded import (
    ERROR_FRAME,
    EXTENDED_ID,
    RecordedRun,
    load_recorded_run,
    recorded_config,
    recorded_design,
    split_json,
)
from rig.replay.result import OPEN_LOOP_NOTE, ReplayResult

__all__ = [
    "ERROR_FRAME",
    "EXTENDED_ID",
    "LOG_SUFFIXES",
    "MAX_LOG_SPAN_S",
    "OPEN_LOOP_NOTE",
    "PIPELINE_MIN_BYTES",
    "BusFault",
    "LogReplayBus",
    "McapReplayBus",
    "RecordedRun",
    "RecordingError",
    "ReplayResult",
    "ScanResult",
    "load_recorded_run",
    "recorded_config",
    "recorded_design",
    "replay_file",
    "replay_log",
    "replay_recording",
    "require_log_reader",
    "scan_recording",
    "split_json",
]
