"""Real-time set-up of the service process, best effort.

Each measure is tried where the platform and the privileges allow it; what could and
could not be had is reported, never raised:

- ``SCHED_FIFO`` priority for the loop thread (``os.sched_setscheduler``; needs
  CAP_SYS_NICE or an rtprio limit), with ``SCHED_RESET_ON_FORK``: a thread or process
  started later from the loop thread (a restarted writer, a helper thread) is an
  ordinary one, never a real-time peer of the loop (systemd's
  ``CPUSchedulingResetOnFork=yes`` does the same for the service's main thread),
- CPU affinity (``os.sched_setaffinity``),
- ``mlockall(MCL_CURRENT | MCL_FUTURE)`` through ctypes (needs CAP_IPC_LOCK or memlock
  limit),
- ``prctl(PR_SET_TIMERSLACK, 1)``: 1 ns timer slack instead of the default 50 us, which
  otherwise makes about half of the wake-ups > 100 us late,
- ``sys.setswitchinterval`` small (100 us): a thread that wakes up waits for the GIL at
  most about this long while another thread (recorder, telemetry, emulated rig) computes,
- a CPU wake-up latency limit of 0 us through ``/dev/cpu_dma_latency`` (PM QoS, held
  open for the life of the process, as ``cyclictest`` does): the CPUs then stay out of
  deep idle states, which otherwise add wake-up latency and flush the caches the tick
  runs from (measured here: tick p50 45 -> 33 us, p99 137 -> 110 us).  Needs root; under
  systemd's DynamicUser use tuned's ``realtime``/``latency-performance`` profile or the
  kernel's ``idle=poll`` instead (docs/deploy.md),
- ``gc.freeze()`` + ``gc.disable()`` after start-up (a full collection of the process
  takes tens of milliseconds; the loop does not allocate in steady state, so nothing
  accumulates).  :func:`restore_gc` undoes it at shutdown.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import struct
import sys
from dataclasses import dataclass, field

__all__ = ["RealtimeReport", "RealtimeRequest", "apply_realtime", "release_cpu_latency",
           "restore_gc"]

log = logging.getLogger(__name__)

_MCL_CURRENT = 1
_MCL_FUTURE = 2
_PR_SET_TIMERSLACK = 29
_PR_GET_TIMERSLACK = 30


@dataclass(frozen=True)
class RealtimeRequest:
    fifo_priority: int = 50          # 0 = do not ask for SCHED_FIFO
    cpus: tuple[int, ...] = ()       # empty = keep the affinity
    lock_memory: bool = True
    timer_slack_ns: int = 1          # 0 = keep the default
    switch_interval_s: float = 0.0001   # GIL hand-over bound for the waking loop thread
    freeze_gc: bool = True
    cpu_latency_us: int | None = 0   # /dev/cpu_dma_latency limit; None = leave it


@dataclass
class RealtimeReport:
    """What was obtained (``granted``) and what was not, with the reason (``denied``)."""

    granted: dict[str, str] = field(default_factory=dict)
    denied: dict[str, str] = field(default_factory=dict)

    def summary(self) -> str:
        got = ", ".join(f"{k}={v}" for k, v in self.granted.items()) or "nothing"
        not_got = ", ".join(f"{k} ({v})" for k, v in self.denied.items()) or "nothing"
        return f"real-time: got {got}; not got {not_got}"

    def as_dict(self) -> dict[str, dict[str, str]]:
        return {"granted": dict(self.granted), "denied": dict(self.denied)}


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name or "libc.so.6", use_errno=True)
    except OSError:
        return None


def _set_fifo(priority: int, report: RealtimeReport) -> None:
    if priority <= 0:
        return
    if not hasattr(os, "sched_setscheduler"):
        report.denied["sched_fifo"] = "not supported on this platform"
        return
    try:
        lo = os.sched_get_priority_min(os.SCHED_FIFO)
        hi = os.sched_get_priority_max(os.SCHED_FIFO)
        prio = max(lo, min(hi, priority))
        # the flag: threads and processes started from this thread do not inherit FIFO
        os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(prio))
        report.granted["sched_fifo"] = str(prio)
    except OSError as exc:
        report.denied["sched_fifo"] = exc.strerror or str(exc)


def _set_affinity(cpus: tuple[int, ...], report: RealtimeReport) -> None:
    if not cpus:
        return
    if not hasattr(os, "sched_setaffinity"):
        report.denied["affinity"] = "not supported on this platform"
        return
    try:
        os.sched_setaffinity(0, set(cpus))
        report.granted["affinity"] = ",".join(str(c) for c in sorted(cpus))
    except (OSError, ValueError) as exc:
        report.denied["affinity"] = getattr(exc, "strerror", None) or str(exc)


def _mlockall(libc: ctypes.CDLL | None, report: RealtimeReport) -> None:
    if libc is None or not hasattr(libc, "mlockall"):
        report.denied["mlockall"] = "libc not available"
        return
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
        report.granted["mlockall"] = "current+future"
    else:
        report.denied["mlockall"] = os.strerror(ctypes.get_errno())


def _timer_slack(libc: ctypes.CDLL | None, slack_ns: int, report: RealtimeReport) -> None:
    if slack_ns <= 0:
        return
    if libc is None or not hasattr(libc, "prctl") or not sys.platform.startswith("linux"):
        report.denied["timer_slack"] = "prctl not available"
        return
    prctl = libc.prctl
    prctl.restype = ctypes.c_int
    if prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) != 0:
        report.denied["timer_slack"] = os.strerror(ctypes.get_errno())
        return
    now = prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
    report.granted["timer_slack"] = f"{now} ns"


_pm_qos_fd: int | None = None    # held open: closing it drops the latency request


def _cpu_latency(limit_us: int | None, report: RealtimeReport) -> None:
    global _pm_qos_fd
    if limit_us is None:
        return
    if _pm_qos_fd is not None:
        report.granted["cpu_latency"] = f"{limit_us} us (already held)"
        return
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        report.denied["cpu_latency"] = f"/dev/cpu_dma_latency: {exc.strerror or exc}"
        return
    try:
        os.write(fd, struct.pack("i", max(0, int(limit_us))))
    except OSError as exc:
        os.close(fd)
        report.denied["cpu_latency"] = f"/dev/cpu_dma_latency: {exc.strerror or exc}"
        return
    _pm_qos_fd = fd
    report.granted["cpu_latency"] = f"{limit_us} us"


def release_cpu_latency() -> None:
    """Drop the /dev/cpu_dma_latency request (shutdown, or tests)."""
    global _pm_qos_fd
    if _pm_qos_fd is not None:
        os.close(_pm_qos_fd)
        _pm_qos_fd = None


def apply_realtime(request: RealtimeRequest | None = None) -> RealtimeReport:
    """Apply ``request`` to the calling thread/process; never raises."""
    req = request or RealtimeRequest()
    report = RealtimeReport()
    libc = _libc()
    for step in (
        lambda: _set_fifo(req.fifo_priority, report),
        lambda: _set_affinity(req.cpus, report),
        lambda: _mlockall(libc, report) if req.lock_memory else None,
        lambda: _timer_slack(libc, req.timer_slack_ns, report),
        lambda: _cpu_latency(req.cpu_latency_us, report),
    ):
        try:
            step()
        except Exception as exc:  # the set-up must never stop the service
            report.denied[f"error{len(report.denied)}"] = repr(exc)
    if req.switch_interval_s > 0:
        sys.setswitchinterval(req.switch_interval_s)
        report.granted["switch_interval"] = f"{sys.getswitchinterval() * 1e6:.0f} us"
    if req.freeze_gc:
        gc.collect()
        gc.freeze()
        gc.disable()
        report.granted["gc"] = "frozen+disabled"
    log.info(report.summary())
    return report


def restore_gc() -> None:
    """Re-enable the garbage collector (shutdown, or tests)."""
    gc.unfreeze()
    gc.enable()
