"""MCAP run recording: raw CAN frames, tick records and events, written by a process of
its own so that the control loop never waits for (or competes with) the encoder.

The 1 kHz loop calls :meth:`RunRecorder.can_frame`, :meth:`RunRecorder.tick_packed`
(a record it packed itself; :meth:`RunRecorder.tick_values` packs one here, the generic
:meth:`RunRecorder.tick` pickles a dict) and :meth:`RunRecorder.event`.  Each packs
the item into a preallocated batch buffer (no JSON, no I/O); every ``cfg.batch_ticks``
ticks the batch goes to a pipe in one non-blocking ``write``.  The writer process
(:mod:`rig.recording.writer`) reads the pipe, encodes JSON, fills MCAP chunks
(``cfg.chunk_bytes``), flushes every finished chunk to the OS and rotates into numbered
files (``rotate_bytes`` / ``rotate_seconds``).  A SIGKILL of the whole service loses at
most the open chunk; a SIGKILL of the loop process alone loses at most the unsent batch:
the writer sees the pipe close and finishes the file.

When the writer falls behind, it holds at most ``cfg.queue_size`` items, then the pipe
(up to ``pipe_bytes``) fills and the loop side drops whole tick batches and counts
every item in :attr:`RunRecorder.dropped`; events of a dropped batch are kept back
(up to 1024) and sent with the next batch, so a fault record survives a frame flood.
``blocking=True`` (offline replay) waits instead of dropping.

Format, channels and the tick-record keys: ``docs/recording.md``.  Reading a run back:
:func:`read_run` (:mod:`rig.recording.run_data`, re-exported here), on top of the one
MCAP reader :mod:`rig.recording.scan`.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import hashlib
import json
import os
import platform
import subprocess
import sys
import threading
import time
import tomllib
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np

from controller.config import RecordingConfig
from rig.output_paths import new_recording_problem, recording_file
from rig.recording.codec import (
    FRAME_ERROR,
    FRAME_EXTENDED,
    FRAME_HEAD,
    FRAME_RX,
    ITEM_EVENT,
    ITEM_FRAME,
    ITEM_HEAD,
    ITEM_LAYOUT,
    TickLayout,
    TickPacker,
    encode_end,
    encode_event,
    encode_header,
    encode_layout,
    encode_pickled_tick,
)
from rig.recording.cpus import leave_the_loops_cpus
from rig.recording.run_data import CanFrameRecord, EventRecord, RunData, TickRecord, read_run
from rig.recording.schema import (
    CONFIG_ATTACHMENT,
    DESIGN_ATTACHMENT,
    METADATA_NAME,
    RECORDING_FORMAT_VERSION,
)
from rig.recording.segments import segment_path
from rig.strict_json import json_lines

__all__ = [
    "CONFIG_ATTACHMENT",
    "DESIGN_ATTACHMENT",
    "METADATA_NAME",
    "CanFrameRecord",
    "EventRecord",
    "RecorderStartError",
    "RunData",
    "RunRecorder",
    "TickLayout",
    "TickRecord",
    "read_run",
    "segment_paths",
]

_EVENT_RETRY = 1024        # events of dropped batches kept back for the next batch
_KEPT_BACK = frozenset({ITEM_EVENT, ITEM_LAYOUT})
_BATCH_BYTES = 1 << 16     # batch buffer; a fuller one is flushed before the next item
_FLUSH_BYTES = 1 << 13     # ... and one this full at the end of a tick


class RecorderStartError(OSError):
    """The writer process could not start or could not open the recording file."""


def segment_paths(base: str | Path) -> list[Path]:
    """``base`` and its existing rotation successors ``<stem>.001.mcap``, ... in order."""
    base = Path(base)
    paths = [base]
    while (nxt := segment_path(base, len(paths))).exists():
        paths.append(nxt)
    return paths


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("lqg-fuzzy-rig", "numpy", "mcap", "eclipse-zenoh", "python-can", "numba"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def _config_hash(config_toml: str) -> str:
    """controller.config.config_hash of the TOML (as the design artifact stores it)."""
    from controller.config import config_hash, parse_config

    try:
        return config_hash(parse_config(tomllib.loads(config_toml)))
    except Exception as exc:  # recorded, never fatal: the raw TOML is attached anyway
        return f"unparseable: {exc}"


class RunRecorder:
    """Record one run into ``path_or_dir`` (a ``.mcap`` file, or a directory that gets
    ``run-<UTC>.mcap``).  Rotation continues in ``<stem>.001.mcap``, ``.002`` ...

    ``t_ns`` arguments must all come from one clock (the loop's; ``clock`` names it for
    the metadata).  MCAP ``log_time`` = ``t_ns + clock_offset_ns`` (default: wall minus
    monotonic at start, so tools show wall time); payloads keep the raw ``t_ns``.

    ``tick_layout`` declares the packed record of :meth:`tick_values`.  The constructor
    starts the writer process and waits until it has opened the first file: a bad path
    or a full disk raises :class:`RecorderStartError` here, not later.  Use from one
    thread (the loop's); the counters may be read from anywhere.
    """

    def __init__(self, path_or_dir: str | Path, cfg: RecordingConfig, *, config_toml: str,
                 design_bytes: bytes | None, metadata: Mapping[str, Any],
                 clock: str = "monotonic", clock_offset_ns: int | None = None,
                 compression: str = "zstd", poll_s: float = 0.002,
                 max_chunk_age_s: float = 1.0, tick_layout: TickLayout | None = None,
                 blocking: bool = False, pipe_bytes: int = 1 << 20,
                 start_timeout_s: float = 60.0) -> None:
        # the writer process runs in another directory
        target = recording_file(path_or_dir).absolute()
        problem = new_recording_problem(target)
        if problem is None:
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                problem = f"cannot create its directory ({exc.strerror or exc})"
        if problem is not None:
            raise RecorderStartError(f"cannot record to {target}: {problem}")
        if compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"compression {compression!r}: allowed zstd, lz4, none")
        self.base_path = target
        self.paths: list[Path] = []
        self.blocking = blocking
        self.batch_ticks = cfg.batch_ticks
        self._ticks_in_batch = 0
        if clock_offset_ns is None:
            clock_offset_ns = time.time_ns() - time.monotonic_ns() if clock == "monotonic" else 0
        #: wall minus loop clock [ns] (the MCAP log_time offset; the live view uses it too)
        self.clock_offset_ns = int(clock_offset_ns)
        self._packer: TickPacker | None = None
        header = {
            "path": str(target), "rotate_bytes": cfg.rotate_bytes,
            "rotate_seconds": cfg.rotate_seconds, "chunk_bytes": cfg.chunk_bytes,
            "queue_size": cfg.queue_size, "compression": compression,
            "clock_offset_ns": int(clock_offset_ns), "poll_s": poll_s,
            "max_chunk_age_s": max_chunk_age_s, "config_toml": config_toml,
            "metadata": self._base_metadata(metadata, clock, int(clock_offset_ns),
                                            config_toml, design_bytes, target),
        }
        self._dropped = 0
        # counters and state reported by the writer process
        self.written = 0             # items written (frames + records + events)
        self.malformed = 0           # items the writer could not encode (skipped)
        self.last_malformed: str | None = None
        self.error: str | None = None
        self._failed = False
        self._closed = False
        self._lock = threading.Lock()   # the status thread updates the counters above
        # the batch of the current tick
        self._batch = bytearray(_BATCH_BYTES)
        self._mv = memoryview(self._batch)
        self._n = 0
        self._items = 0
        self._kept_in_batch = 0
        self._pending: bytes = b""             # tail of a partially written batch
        self._retry: collections.deque[bytes] = collections.deque(maxlen=_EVENT_RETRY)

        self._proc = subprocess.Popen(
            [sys.executable, "-m", "rig.recording.writer"], stdin=subprocess.PIPE,
            # cwd: where `-m rig.recording.writer` finds this very copy of the package
            # (the directory holding rig/; an installed copy elsewhere must not stand in)
            stdout=subprocess.PIPE, cwd=Path(__file__).resolve().parents[2],
            start_new_session=True, text=False)
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._fd = self._proc.stdin.fileno()
        with contextlib.suppress(OSError):   # best effort: the default pipe is 64 KiB
            fcntl.fcntl(self._fd, fcntl.F_SETPIPE_SZ, max(4096, int(pipe_bytes)))
        self._ready = threading.Event()
        self._status_thread = threading.Thread(target=self._read_status,
                                               name="rig-recorder-status", daemon=True)
        self._status_thread.start()
        with contextlib.suppress(OSError):   # if the writer failed, its status says why
            self._write_all(encode_header(header, design_bytes))
        if not self._ready.wait(start_timeout_s) or self.error is not None:
            reason = self.error or f"writer process did not start within {start_timeout_s} s"
            self._kill_writer()
            raise RecorderStartError(f"recording {target}: {reason}")
        if tick_layout is not None:
            self.set_tick_layout(tick_layout)
        if not blocking:
            os.set_blocking(self._fd, False)

    # ------------------------------------------------------------------ status
    @property
    def dropped(self) -> int:
        """Items not recorded because the writer fell behind, failed or was closed."""
        return self._dropped

    @property
    def pid(self) -> int:
        """PID of the writer process."""
        return self._proc.pid

    def _read_status(self) -> None:
        leave_the_loops_cpus()          # this thread does not share the loop's CPU
        out = self._proc.stdout
        assert out is not None
        for st in json_lines(out):
            ev = st.get("event")
            with self._lock:
                if ev == "error":
                    self.error = str(st.get("error"))
                    self._failed = True
                else:
                    self.written = int(st.get("written", self.written))
                    self.malformed = int(st.get("malformed", self.malformed))
                    self.last_malformed = st.get("last_malformed", self.last_malformed)
                    self.paths = [Path(p) for p in st.get("paths", [])] or self.paths
                    if st.get("error"):
                        self.error = str(st["error"])
                        self._failed = True
            if ev in ("ready", "error"):
                self._ready.set()
        with self._lock:
            if not self._closed and self.error is None:
                self.error = "writer process ended unexpectedly"
            self._failed = True
        self._ready.set()

    # ------------------------------------------------------------------ loop side (cheap)
    def can_frame(self, t_ns: int, tick: int, arbitration_id: int,
                  data: bytes | bytearray | memoryview,
                  is_rx: bool, error_frame: bool = False, extended_id: bool = False) -> bool:
        """Add one raw frame to this tick's batch (``data`` is copied).  Never blocks;
        False = dropped (writer failed or closed).  Sent with the next tick record."""
        if self._failed or self._closed:
            self._dropped += 1
            return False
        dlc = len(data)
        size = FRAME_HEAD.size + dlc
        if self._n + size > _BATCH_BYTES:
            self.flush()
        n = self._n
        FRAME_HEAD.pack_into(self._batch, n, size, ITEM_FRAME, t_ns, tick, arbitration_id,
                             (FRAME_RX if is_rx else 0) | (FRAME_ERROR if error_frame else 0)
                             | (FRAME_EXTENDED if extended_id else 0), dlc)
        self._mv[n + FRAME_HEAD.size:n + size] = data
        self._n = n + size
        self._items += 1
        return True

    def set_tick_layout(self, layout: TickLayout) -> None:
        """Declare the packed record of :meth:`tick_values` (again when it changes, e.g.
        another design); the writer applies it to the records that follow."""
        if self._packer is not None and self._packer.layout == layout:
            return
        self._packer = TickPacker(layout)
        if not (self._failed or self._closed):
            self._send_bytes(encode_layout(layout), keep=True)

    def tick_values(self, t_ns: int, scalars: Sequence[Any], arrays: Sequence[np.ndarray]
                    ) -> bool:
        """Add the packed tick record (``tick_layout`` order; arrays are copied at once);
        the tick's items are sent every ``batch_ticks`` ticks.  False = the batch this
        call sent was dropped."""
        packer = self._packer
        if packer is None:
            raise ValueError("tick_values needs a RunRecorder made with a tick_layout")
        if self._failed or self._closed:
            self._dropped += 1
            return False
        size = packer.size
        if self._n + size > _BATCH_BYTES:
            self.flush()
        packer.pack(t_ns, scalars, arrays)
        n = self._n
        if size > _BATCH_BYTES:
            self._send_bytes(bytes(packer.buffer))
            return self.flush()
        self._mv[n:n + size] = packer.buffer
        self._n = n + size
        self._items += 1
        return self._end_of_tick()

    def tick_packed(self, record: bytes | bytearray | memoryview) -> bool:
        """Add a tick record packed already (one ``ITEM_TICK`` of the declared
        ``tick_layout``, e.g. the loop's :class:`TickPacker` buffer, copied at once: the
        loop packs a tick once for the recording and the telemetry process); sent like
        :meth:`tick_values`' records.  False = the batch this call sent was dropped."""
        packer = self._packer
        if packer is None:
            raise ValueError("tick_packed needs a RunRecorder made with a tick_layout")
        size = len(record)
        if size != packer.size:
            raise ValueError(f"tick record of {size} bytes, the layout's are {packer.size}")
        if self._failed or self._closed:
            self._dropped += 1
            return False
        if self._n + size > _BATCH_BYTES:
            self.flush()
        if size > _BATCH_BYTES:
            self._send_bytes(bytes(record))
            return self.flush()
        n = self._n
        self._mv[n:n + size] = record
        self._n = n + size
        self._items += 1
        return self._end_of_tick()

    def _end_of_tick(self) -> bool:
        self._ticks_in_batch += 1
        if self._ticks_in_batch >= self.batch_ticks or self._n >= _FLUSH_BYTES:
            return self.flush()
        return True

    def tick(self, t_ns: int, record: Mapping[str, Any]) -> bool:
        """Add one tick record given as a flat dict (pickled now: arrays may be reused by
        the caller afterwards), like :meth:`tick_values`.  The loop uses that one."""
        if self._failed or self._closed:
            self._dropped += 1
            return False
        try:
            blob = encode_pickled_tick(t_ns, record)
        except Exception as exc:                # unpicklable: skipped, counted
            with self._lock:
                self.malformed += 1
                self.last_malformed = f"{type(exc).__name__}: {exc} in tick record"
            return False
        self._send_bytes(blob)
        return self._end_of_tick()

    def event(self, t_ns: int, tick: int, kind: str, detail: Mapping[str, Any] | str | None
              ) -> bool:
        """Add a lifecycle / command / fault / note event (sent with the tick's batch).
        An event in a dropped batch is kept back and sent with a later one."""
        if self._failed or self._closed:
            self._dropped += 1
            return False
        self._send_bytes(encode_event(t_ns, tick, kind, detail), keep=True)
        return True

    def _send_bytes(self, blob: bytes, keep: bool = False) -> None:
        if self._n + len(blob) > _BATCH_BYTES:
            self.flush()
        if len(blob) > _BATCH_BYTES:            # a huge item: its own write
            self._items += 1
            self._kept_in_batch += keep
            self._deliver(memoryview(blob), len(blob))
            return
        n = self._n
        self._mv[n:n + len(blob)] = blob
        self._n = n + len(blob)
        self._items += 1
        self._kept_in_batch += keep

    def flush(self) -> bool:
        """Send the batch now.  False = it was dropped (pipe full or writer gone)."""
        self._ticks_in_batch = 0
        if self._n == 0:
            return True
        return self._deliver(self._mv[:self._n], self._n)

    def _deliver(self, data: memoryview, n: int) -> bool:
        items = self._items
        ok = True
        if self._retry and not self._pending:
            self._push_retry()
        if self._pending and not self._push_pending():
            ok = False
        elif self._retry:
            ok = False                         # keep the order: events first
        else:
            try:
                w = os.write(self._fd, data) if not self.blocking else self._write_all(data)
            except BlockingIOError:
                ok = False
            except OSError as exc:
                self._writer_gone(exc)
                ok = False
            else:
                if w < n:
                    self._pending = bytes(data[w:])
        if not ok:
            self._drop_batch(data, items)
        self._n = 0
        self._items = 0
        self._kept_in_batch = 0
        return ok

    def _drop_batch(self, data: memoryview, items: int) -> None:
        """Count the batch's items as dropped, keeping its events and tick layout back
        for later (without its layout the writer could not decode what follows)."""
        kept = 0
        if self._kept_in_batch and not self._failed:
            pos = 0
            while pos < len(data):
                size, kind = ITEM_HEAD.unpack_from(data, pos)
                if kind in _KEPT_BACK and len(self._retry) < _EVENT_RETRY:
                    self._retry.append(bytes(data[pos:pos + size]))
                    kept += 1
                pos += size
        self._dropped += items - kept

    def _push_pending(self) -> bool:
        try:
            w = os.write(self._fd, self._pending)
        except BlockingIOError:
            return False
        except OSError as exc:
            self._writer_gone(exc)
            return False
        self._pending = self._pending[w:]
        return not self._pending

    def _push_retry(self) -> None:
        while self._retry:
            blob = self._retry[0]
            try:
                w = os.write(self._fd, blob)
            except BlockingIOError:
                return
            except OSError as exc:
                self._writer_gone(exc)
                return
            self._retry.popleft()
            if w < len(blob):
                self._pending = blob[w:]
                return

    def _write_all(self, data: bytes | memoryview) -> int:
        view = memoryview(data)
        done = 0
        while done < len(view):
            done += os.write(self._fd, view[done:])
        return done

    def _writer_gone(self, exc: OSError) -> None:
        self._failed = True
        if self.error is None:
            self.error = f"writer process gone ({type(exc).__name__}: {exc})"
        self._dropped += len(self._retry)
        self._retry.clear()
        self._pending = b""

    # ------------------------------------------------------------------ closing
    def close(self, timeout_s: float = 30.0) -> None:
        """Send what is left, let the writer drain and finish the file (summary and
        footer), wait for it (``timeout_s``).  Idempotent."""
        if self._closed:
            return
        if not self._failed:
            # the loop has stopped: the last batch (the safe command, the final events)
            # waits for the writer instead of being dropped when the pipe is full
            os.set_blocking(self._fd, True)
            self.blocking = True
        self.flush()
        self._closed = True
        fd_ok = not self._failed
        if fd_ok:
            try:
                for blob in self._retry:
                    self._write_all(blob)
                self._retry.clear()
                if self._pending:
                    self._write_all(self._pending)
                self._pending = b""
                self._write_all(encode_end())
            except OSError as exc:
                self._writer_gone(exc)
        with contextlib.suppress(OSError):
            assert self._proc.stdin is not None
            self._proc.stdin.close()
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.error = self.error or f"writer did not finish within {timeout_s} s"
            self._kill_writer()
        self._status_thread.join(5.0)
        if self._proc.returncode not in (0, None) and self.error is None:
            self.error = f"writer process exited with status {self._proc.returncode}"

    def _kill_writer(self) -> None:
        with contextlib.suppress(OSError):
            self._proc.kill()              # our own child, by its Popen handle
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(5.0)

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ metadata
    @staticmethod
    def _base_metadata(user: Mapping[str, Any], clock: str, offset: int, config_toml: str,
                       design: bytes | None, target: Path) -> dict[str, str]:
        meta = {
            "format_version": str(RECORDING_FORMAT_VERSION),
            "run_id": uuid.uuid4().hex,      # one per run, in every segment
            "run_name": target.stem,
            "created_utc": datetime.now(UTC).isoformat(),
            "clock": clock,
            "clock_offset_ns": str(offset),
            "config_hash": _config_hash(config_toml),
            "config_toml_sha256": hashlib.sha256(config_toml.encode()).hexdigest(),
            "design_sha256": hashlib.sha256(design).hexdigest() if design is not None else "",
            "versions": json.dumps(_versions(), sort_keys=True),
        }
        for k, v in user.items():
            meta[str(k)] = v if isinstance(v, str) else json.dumps(v, default=str)
        return meta
