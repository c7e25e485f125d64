"""The loop process's side of the telemetry process: start it, feed it, supervise it.

:class:`TelemetryLink` starts ``python -m rig.telemetry_process`` (the Zenoh session and
the live Foxglove server, :mod:`rig.telemetry_process.child`) and feeds it through a
pipe, as :class:`rig.recording.recorder.RunRecorder` feeds its writer:

- the loop thread calls :meth:`TelemetryLink.offer_packed` every :attr:`tick_every`
  ticks with the tick record it packed for the recording
  (:class:`rig.recording.codec.TickPacker`): one non-blocking ``write``, no JSON; and
  :meth:`TelemetryLink.offer_event` for each event; a full pipe (the process is slow)
  or a dead process drops the item and counts it (:attr:`dropped`, the tick record's
  ``dropped_telemetry``);
- a status thread builds the service's status every :data:`STATUS_PERIOD_S` (off the
  loop thread) and leaves it for the loop thread, which writes it with its next tick
  record: the process answers ``rig/status`` queries from it and never calls into the
  loop process.  The loop thread wakes the status thread right after it wrote a tick
  record (every :data:`STATUS_PERIOD_S` of records), so that the build, ~20 us of
  Python holding the interpreter lock (``Service.status()`` and its pickle, 864 bytes:
  21 us p50 / 47 us p99 on the 2-core VM, 2026-11-28; most of it the timing
  percentiles), runs while the loop sleeps until its next deadline instead of at a
  random moment (a loop thread woken while another thread holds the lock waits for
  it, up to the switch interval, 100 us);
- operator commands come back as JSON lines on the process's stdout.  A supervisor
  thread reads them (at most 8 KiB every 5 ms, lines over :data:`MAX_LINE_BYTES`
  dropped) into a bounded queue; the loop thread takes at most one per
  :meth:`TelemetryLink.poll`, validates it again (:func:`rig.operator_commands.validate_command`)
  and applies it; the reply goes back on the feed.  Nothing the process sends is
  unpickled or trusted;
- when the process dies (SIGKILL, a crash of the SDK) control goes on: the supervisor
  logs it, the loop records a ``note`` event (``{"telemetry_process": "lost", ...}``),
  ``status()["telemetry"]["process"]`` and systemd's ``STATUS=`` say so, and the process
  is restarted after 0.5, 1, 2, 4, 8 s, at most :data:`RESTART_ATTEMPTS` times in a run;
  after that it stays down and the status says why.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Final, Protocol

from controller.config import RigConfig, config_to_toml
from rig.operator_commands import OPERATOR_COMMANDS, brief, loop_argument, validate_command
from rig.recording.codec import TickLayout, encode_end, encode_event, encode_layout
from rig.recording.cpus import leave_the_loops_cpus, loop_cpus_env
from rig.telemetry_process.feed import (
    MAX_LINE_BYTES,
    STATUS_PERIOD_S,
    encode_feed_header,
    encode_reply,
    encode_status,
)

__all__ = ["COMMAND_QUEUE", "RESTART_ATTEMPTS", "CommandTarget", "TelemetryLink"]

log = logging.getLogger(__name__)

#: restarts of a lost telemetry process in one run; after that it stays down
RESTART_ATTEMPTS: Final = 5
#: pause before the first restart [s]; doubled for each further one, at most 8 s
RESTART_PAUSE_S: Final = 0.5
_RESTART_PAUSE_MAX_S: Final = 8.0
#: operator commands waiting for the loop; more are dropped (and counted)
COMMAND_QUEUE: Final = 16
#: the supervisor reads at most _READ_BYTES of the process's lines every _READ_PAUSE_S
#: (1.6 MB/s: its state is ~2 kB/s, commands are rate-limited), so that however much a
#: misbehaving process writes, parsing it holds this process's GIL ~2 % of the time
_READ_BYTES: Final = 8192
_READ_PAUSE_S: Final = 0.005


class CommandTarget(Protocol):
    """What :meth:`TelemetryLink.poll` needs of the loop (``rig.service.loop.ControlLoop``)."""

    def request(self, name: str, argument: Any = None, timeout_s: float | None = 1.0
                ) -> Any: ...
    def record_note(self, detail: Mapping[str, Any]) -> None: ...


class _Child:
    """One incarnation of the telemetry process."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdin is not None and proc.stdout is not None
        self.proc = proc
        self.fd = proc.stdin.fileno()
        self.out_fd = proc.stdout.fileno()
        self.alive = True
        self.pending = b""          # tail of an item the pipe took only in part
        self.ready = threading.Event()


class _FoxgloveReport:
    """The live view as the telemetry process last reported it (``Service.foxglove``)."""

    def __init__(self, link: TelemetryLink) -> None:
        self._link = link

    def status(self) -> dict[str, Any]:
        return dict(self._link.foxglove_status)

    @property
    def state(self) -> str:
        return str(self._link.foxglove_status.get("state", "starting"))

    @property
    def url(self) -> str | None:
        url = self._link.foxglove_status.get("url")
        return None if url is None else str(url)

    @property
    def port(self) -> int:
        return int(self._link.foxglove_status.get("port") or 0)

    @property
    def subprotocol(self) -> str:
        """The WebSocket subprotocol the view serves (the SDK's, as the process said)."""
        return str(self._link.foxglove_status.get("subprotocol") or "")

    @property
    def error(self) -> str | None:
        error = self._link.foxglove_status.get("error")
        return None if error is None else str(error)


class TelemetryLink:
    """The telemetry process of one service (see the module docstring).

    ``zenoh`` / ``foxglove``: which surfaces the process serves (at least one).
    ``status_provider()``: the service's status (plain values), called on the status
    thread.  ``on_note(key, text)``: a standing condition for systemd's STATUS= (None
    clears it), called from the supervisor thread; must not block."""

    def __init__(self, cfg: RigConfig, layout: TickLayout, *, zenoh: bool, foxglove: bool,
                 status_provider: Callable[[], Mapping[str, Any]],
                 clock_offset_ns: int | None = None, name: str = "rig",
                 on_note: Callable[[str, str | None], None] | None = None,
                 restart_attempts: int = RESTART_ATTEMPTS,
                 restart_pause_s: float = RESTART_PAUSE_S,
                 start_timeout_s: float = 60.0, pipe_bytes: int = 1 << 18) -> None:
        if not (zenoh or foxglove):
            raise ValueError("a telemetry process serves Zenoh, Foxglove or both")
        rate = cfg.design.sample_rate_hz
        rates = ([cfg.telemetry.rate_hz] if zenoh else []) + \
            ([cfg.foxglove.rate_hz] if foxglove else [])
        #: the loop hands a tick record every this many ticks (the faster surface's rate)
        self.tick_every = max(1, round(rate / max(rates)))
        self.zenoh_on, self.foxglove_on = zenoh, foxglove
        self.restart_attempts = restart_attempts
        self._restart_pause_s = restart_pause_s
        self._pipe_bytes = pipe_bytes
        self._status_provider = status_provider
        self._on_note = on_note
        #: bytes of one packed tick record of ``layout``
        self._record_size = layout.item_size()
        offset = (time.time_ns() - time.monotonic_ns() if clock_offset_ns is None
                  else int(clock_offset_ns))
        self._header = encode_feed_header({
            "config_toml": config_to_toml(cfg), "layout": layout.to_json(),
            "zenoh": zenoh, "foxglove": foxglove, "clock_offset_ns": offset, "name": name,
            "log_level": logging.getLogger().getEffectiveLevel()})
        self._layout_item = encode_layout(layout)
        # loop side (the loop thread only)
        self.dropped = 0             # items the feed could not take
        self.sent = 0
        # filled by the supervisor thread
        self._commands: collections.deque[tuple[int, str, Any]] = collections.deque()
        self.commands_dropped = 0    # commands over COMMAND_QUEUE
        self.lines_dropped = 0       # lines from the process that were not understood
        self._notes: collections.deque[dict[str, Any]] = collections.deque(maxlen=64)
        self.zenoh_status: dict[str, Any] = ({"state": "connecting"} if zenoh
                                             else {"state": "off"})
        self.foxglove_status: dict[str, Any] = ({"state": "starting"} if foxglove
                                                else {"state": "off"})
        self.process_state = "starting"
        self.restarts = 0
        self.losses = 0
        self.last_loss: str | None = None
        self._connected = threading.Event()
        self._settled = threading.Event()
        self._closing = threading.Event()
        #: set by the loop thread after a tick record: time to build the status
        self._status_due = threading.Event()
        self._status_every = max(1, round(STATUS_PERIOD_S * rate / self.tick_every))
        self._records = 0            # tick records offered since the last status
        self._status_blob: bytes | None = None
        self.foxglove = _FoxgloveReport(self)
        self._child: _Child | None = None
        self._child = self._spawn()
        self._supervisor = threading.Thread(target=self._supervise, args=(self._child,),
                                            name="rig-telemetry-link", daemon=True)
        self._supervisor.start()
        self._status_thread = threading.Thread(target=self._build_status,
                                               name="rig-status", daemon=True)
        self._status_thread.start()
        if not self._child.ready.wait(start_timeout_s) and self.process_state == "starting":
            log.error("telemetry process did not start within %.0f s; control goes on "
                      "without it", start_timeout_s)

    # ------------------------------------------------------------------ loop side
    def offer_packed(self, record: bytes | bytearray | memoryview) -> bool:
        """Write a tick record the loop packed already (one ``ITEM_TICK`` of the layout
        this link was made with: the bytes the recording gets) and the status, when one
        is waiting.  Never blocks; False (and ``dropped`` += 1) when it was not taken."""
        child = self._child
        if child is None or not child.alive:
            self.dropped += 1
            return False
        if len(record) != self._record_size:
            raise ValueError(f"tick record of {len(record)} bytes, the layout's are "
                             f"{self._record_size}")
        status = self._status_blob
        if status is not None:
            self._status_blob = None
            self._send(child, status)
        taken = self._send(child, record)
        self._records += 1
        if self._records >= self._status_every:
            # the status is built now, while the loop sleeps until its next deadline
            self._records = 0
            self._status_due.set()
        return taken

    def offer_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool:
        """An event (lifecycle, fault, command, note) for the live view; False when
        dropped."""
        child = self._child
        if child is None or not child.alive:
            self.dropped += 1
            return False
        return self._send(child, encode_event(t_ns, tick, kind, detail))

    def poll(self, loop: CommandTarget) -> None:
        """Loop thread, at its own pace: record the losses of the process as notes,
        apply at most one operator command (validated again here) and send its reply."""
        while self._notes:
            loop.record_note(self._notes.popleft())
        if not self._commands:
            return
        cid, name, args = self._commands.popleft()
        try:
            validate_command(name, args)
            res = loop.request(name, loop_argument(name, args), timeout_s=None)
            accepted, message = bool(res.accepted), str(res.message)
        except (ValueError, TypeError, KeyError) as exc:
            accepted, message = False, str(exc)[:200]
        child = self._child
        if child is not None and child.alive:
            self._send(child, encode_reply(cid, accepted, message))

    def _send(self, child: _Child, data: bytes | bytearray | memoryview) -> bool:
        try:
            if child.pending:
                w = os.write(child.fd, child.pending)
                child.pending = child.pending[w:]
                if child.pending:
                    self.dropped += 1
                    return False
            w = os.write(child.fd, data)
        except BlockingIOError:
            self.dropped += 1
            return False
        except OSError:                 # EPIPE: the process is gone (the supervisor says)
            child.alive = False
            child.pending = b""
            self.dropped += 1
            return False
        if w < len(data):
            child.pending = bytes(data[w:])
        self.sent += 1
        return True

    # ------------------------------------------------------------------ outside
    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout_s: float) -> bool:
        """Wait until the Zenoh session of the process is up."""
        return self._connected.wait(timeout_s)

    def wait_settled(self, timeout_s: float) -> bool:
        """Wait until the Zenoh session is up or has failed for good; False on timeout."""
        return self._settled.wait(timeout_s)

    @property
    def error(self) -> str | None:
        """Why the Zenoh session is not up (as the process reported it), or why the
        process is down."""
        error = self.zenoh_status.get("error")
        if error is None and self.process_state == "lost":
            return self.last_loss
        return None if error is None else str(error)

    @property
    def pid(self) -> int | None:
        child = self._child
        return None if child is None or not child.alive else child.proc.pid

    def status(self) -> dict[str, Any]:
        """The Zenoh telemetry as the process last reported it, with the process's own
        state (``process``) and the feed's drops (any thread)."""
        child = self._child
        return {**self.zenoh_status, "feed_dropped": self.dropped,
                "commands_dropped": self.commands_dropped,
                "process": {"state": self.process_state,
                            "pid": None if child is None else child.proc.pid,
                            "restarts": self.restarts,
                            "restart_attempts": self.restart_attempts,
                            "losses": self.losses, "last_loss": self.last_loss}}

    def close(self, timeout_s: float = 10.0) -> None:
        """End the process (an END item, then its stdin closed; killed after
        ``timeout_s``) and the threads.  Idempotent."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._status_due.set()
        child = self._child
        if child is not None:
            if child.alive and not child.pending:
                # never waits: a process that does not read gets its stdin closed instead
                with contextlib.suppress(OSError):
                    os.write(child.fd, encode_end())
            with contextlib.suppress(OSError):
                assert child.proc.stdin is not None
                child.proc.stdin.close()
            try:
                rc = child.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("telemetry process did not end within %.0f s: killed", timeout_s)
                self._kill(child)
            else:
                if rc != 0 and child.alive:
                    log.warning("telemetry process ended with exit status %d", rc)
        self._supervisor.join(5.0)
        self._status_thread.join(5.0)
        self.process_state = "stopped"

    def __enter__(self) -> TelemetryLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ process
    def _spawn(self, loop_cpus: set[int] | None = None) -> _Child:
        """Start the process from the calling thread's CPUs; ``loop_cpus``: the loop's,
        which the calling thread left already (the process is told them and stays off
        them, from its first instruction on)."""
        proc = subprocess.Popen(
            [sys.executable, "-m", "rig.telemetry_process"], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, cwd=Path(__file__).resolve().parents[2],
            start_new_session=True, env=loop_cpus_env(loop_cpus))
        child = _Child(proc)
        with contextlib.suppress(OSError):   # best effort: the default pipe is 64 KiB
            fcntl.fcntl(child.fd, fcntl.F_SETPIPE_SZ, max(4096, self._pipe_bytes))
        try:          # the process reads its header at once: this does not wait long
            os.write(child.fd, self._header + self._layout_item)
        except OSError:
            child.alive = False
        os.set_blocking(child.fd, False)
        return child

    @staticmethod
    def _kill(child: _Child) -> None:
        with contextlib.suppress(OSError):
            child.proc.kill()          # our own child, by its Popen handle
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.proc.wait(5.0)

    def _supervise(self, child: _Child) -> None:
        # off the loop's CPU; a restarted process starts here too, told the loop's CPUs
        # (its interpreter's start and imports, ~0.2 s of CPU, stay off the running loop's
        # CPU; the first process started before the loop ran)
        loop_cpus = leave_the_loops_cpus()
        while True:
            self._read(child)
            rc = child.proc.wait()
            child.alive = False
            child.ready.set()
            if self._closing.is_set():
                return
            self.losses += 1
            how = f"killed by signal {-rc}" if rc < 0 else f"exit status {rc}"
            if self.restarts >= self.restart_attempts:
                self.process_state = "lost"
                why = (f"telemetry process lost ({how}); not restarted: it was restarted "
                       f"{self.restarts} times already (the limit); control goes on "
                       "without telemetry")
                self._lost(why, rc, None)
                return
            pause = min(self._restart_pause_s * 2 ** self.restarts, _RESTART_PAUSE_MAX_S)
            self.process_state = "restarting"
            self._lost(f"telemetry process lost ({how}); control goes on, restart "
                       f"{self.restarts + 1} of {self.restart_attempts} in {pause:g} s",
                       rc, pause)
            if self._closing.wait(pause):
                return
            try:
                child = self._spawn(loop_cpus)
            except OSError as exc:
                self.process_state = "lost"
                self._lost(f"telemetry process not restarted: {exc}", rc, None)
                return
            self.restarts += 1
            self._child = child

    def _lost(self, why: str, rc: int, restart_in_s: float | None) -> None:
        log.error("%s", why)
        self.last_loss = why
        self._connected.clear()
        self.zenoh_status = {**self.zenoh_status, "state": "lost"} if self.zenoh_on \
            else self.zenoh_status
        if self.foxglove_on:
            self.foxglove_status = {**self.foxglove_status, "state": "lost", "url": None}
        self._notes.append({"telemetry_process": "lost", "exit_status": rc,
                            "restarts": self.restarts, "restart_in_s": restart_in_s,
                            "reason": why})
        self._note("telemetry", f"LOST: {why}")

    def _note(self, key: str, text: str | None) -> None:
        if self._on_note is not None:
            try:
                self._on_note(key, text)
            except Exception:
                log.exception("telemetry note callback")

    def _read(self, child: _Child) -> None:
        """The process's JSON lines until it ends (its stdout closes)."""
        buf = b""
        while True:
            try:
                data = os.read(child.out_fd, _READ_BYTES)
            except OSError:
                data = b""
            if not data:
                return
            buf += data
            *lines, buf = buf.split(b"\n")
            for line in lines:
                if len(line) > MAX_LINE_BYTES:
                    self.lines_dropped += 1
                else:
                    self._on_line(child, line)
            if len(buf) > MAX_LINE_BYTES:
                self.lines_dropped += 1
                buf = b""
            time.sleep(_READ_PAUSE_S)   # however much it sends, this thread mostly sleeps

    def _on_line(self, child: _Child, line: bytes) -> None:
        try:
            msg = json.loads(line)
            event = msg["event"]
        except (ValueError, TypeError, KeyError):
            self.lines_dropped += 1
            return
        if event == "command":
            cid, name, args = msg.get("id"), msg.get("name"), msg.get("args")
            if not (isinstance(cid, int) and isinstance(name, str)):
                self.lines_dropped += 1
            elif len(self._commands) >= COMMAND_QUEUE:
                self.commands_dropped += 1
            else:
                self._commands.append((cid, name if name in OPERATOR_COMMANDS
                                       else brief(name), args))
            return
        if event in ("ready", "state", "final"):
            tel, fox = msg.get("telemetry"), msg.get("foxglove")
            # a (re)started process first clears the loss note, then its own state may set
            # one again (a "ready" that already carries a failed session keeps it noted)
            if event == "ready" and self.process_state in ("starting", "restarting"):
                if self.process_state == "restarting":
                    log.warning("telemetry process restarted (pid %d)", child.proc.pid)
                self._note("telemetry", None)
                self.process_state = "running"
            if self.zenoh_on and isinstance(tel, dict):
                self._zenoh_state(tel)
            if self.foxglove_on and isinstance(fox, dict):
                self._foxglove_state(fox)
            if event == "ready":
                child.ready.set()
            return
        self.lines_dropped += 1

    def _zenoh_state(self, tel: dict[str, Any]) -> None:
        before = self.zenoh_status.get("state")
        self.zenoh_status = tel
        state = tel.get("state")
        if state == "connected":
            self._connected.set()
            self._settled.set()
        elif state == "failed":
            self._settled.set()
        if state != before:
            if state == "connected":
                self._note("telemetry", None)
            elif state in ("retrying", "failed"):
                self._note("telemetry", f"{str(state).upper()}: {tel.get('error')}")

    def _foxglove_state(self, fox: dict[str, Any]) -> None:
        before = self.foxglove_status.get("state")
        self.foxglove_status = fox
        if fox.get("state") != before and fox.get("state") == "failed":
            self._note("foxglove", str(fox.get("error")))

    def _build_status(self) -> None:
        """Status thread: the service's status when the loop thread asks for it (every
        STATUS_PERIOD_S, right after a tick record), pickled here and left for the loop
        thread to write (it alone writes the pipe)."""
        leave_the_loops_cpus()          # this thread does not share the loop's CPU
        while True:
            self._status_due.wait()
            self._status_due.clear()
            if self._closing.is_set():
                return
            try:
                self._status_blob = encode_status(self._status_provider())
            except Exception as exc:   # a status that cannot be built is no reason to stop
                self._status_blob = encode_status(
                    {"error": f"status: {type(exc).__name__}: {str(exc)[:200]}"})
