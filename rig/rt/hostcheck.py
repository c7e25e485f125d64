"""Can this computer run the rig loop?  Wake-up latency against the loop's budgets.

:func:`measure_wakeup` paces a thread exactly as the control loop does (the same
:class:`rig.rt.pacing.Pacer`: absolute deadlines, sleep to ``LOOP_SPIN_NS`` before the
deadline, spin the rest, skip whole missed periods) and records how late each wake-up
was.  It measures in the calling thread with whatever real-time set-up that thread has;
:func:`check_host` applies the loop's own set-up (:func:`rig.rt.realtime.apply_realtime`)
first when given a request.

:func:`verdict` is pure: the latencies against the :class:`Budget` of a configuration.
The host fails when

* the worst wake-up is at least ``safety.stale_ticks`` periods late (the loop would see
  no fresh SensorData for longer than that: SENSOR_STALE; the rig's drive watchdog sees
  no ValveCommand), or
* the p99 lateness reaches ``safety.overrun_threshold_s`` (overruns are then routine and
  ``safety.overrun_streak`` of them in a row are a matter of time: OVERRUN_STREAK).

A p99.99 above the overrun threshold alone is a note, not a failure.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike

from controller.config import RigConfig
from rig.rt.pacing import LOOP_SPIN_NS, Pacer
from rig.rt.realtime import RealtimeReport, RealtimeRequest, apply_realtime, restore_gc

__all__ = ["Budget", "HostCheck", "Latency", "Verdict", "check_host",
           "measure_wakeup", "summarise", "verdict"]

DOCS = "docs/deploy.md"


@dataclass(frozen=True)
class Budget:
    """The loop's timing budgets [s] (owned by ``[design]`` and ``[safety]``)."""

    period_s: float
    stale_ticks: int
    overrun_threshold_s: float

    @property
    def stale_s(self) -> float:
        """``safety.stale_ticks`` x period: a wake-up this late starves the loop."""
        return self.stale_ticks * self.period_s

    @classmethod
    def from_config(cls, cfg: RigConfig) -> Budget:
        return cls(cfg.sample_time_s, cfg.safety.stale_ticks, cfg.safety.overrun_threshold_s)


@dataclass(frozen=True)
class Latency:
    """Wake-up lateness (wake-up minus deadline) [s] over ``samples`` wake-ups."""

    samples: int
    p50_s: float
    p99_s: float
    p9999_s: float
    max_s: float
    skipped: int = 0          # deadlines skipped because a wake-up was a period late

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def summarise(lateness_s: ArrayLike, skipped: int = 0) -> Latency:
    """:class:`Latency` of an array of lateness values [s]."""
    x = np.asarray(lateness_s, dtype=np.float64).ravel()
    if x.size == 0:
        nan = math.nan
        return Latency(0, nan, nan, nan, nan, skipped)
    p50, p99, p9999 = np.percentile(x, [50.0, 99.0, 99.99])
    return Latency(int(x.size), float(p50), float(p99), float(p9999), float(np.max(x)),
                   int(skipped))


def measure_wakeup(period_s: float, seconds: float, *, spin_ns: int = LOOP_SPIN_NS,
                   clock: Callable[[], int] = time.monotonic_ns,
                   sleep: Callable[[float], None] = time.sleep) -> Latency:
    """Pace the calling thread at ``period_s`` for ``seconds`` as the loop does; the
    lateness of its wake-ups."""
    period_ns = max(1, round(period_s * 1e9))
    n = max(1, math.ceil(seconds / period_s))
    late = np.empty(n, dtype=np.int64)       # preallocated: nothing allocates per tick
    pacer = Pacer(period_ns, start_ns=clock() + period_ns, spin_ns=spin_ns, clock=clock,
                  sleep=sleep)
    end_ns = pacer.deadline + round(seconds * 1e9)
    i = 0
    while i < n and pacer.deadline < end_ns:
        late[i] = pacer.wait() - pacer.deadline
        i += 1
        pacer.advance()
    return summarise(late[:i] * 1e-9, pacer.skipped)


@dataclass(frozen=True)
class Verdict:
    ok: bool
    problems: tuple[str, ...]     # why the loop would not hold its budgets
    notes: tuple[str, ...]        # worth knowing, not failing
    advice: tuple[str, ...]       # what to change (empty when ok)

    def line(self) -> str:
        """One line: 'host holds the loop's timing budgets' or the first problem."""
        if self.ok:
            return "host holds the loop's timing budgets"
        return "host does not hold the loop's timing budgets: " + "; ".join(self.problems)


def _us(x: float) -> str:
    return f"{x * 1e6:.0f} us"


def verdict(lat: Latency, budget: Budget, *, realtime: Mapping[str, Mapping[str, str]]
            | None = None, kernel: str | None = None) -> Verdict:
    """Judge ``lat`` against ``budget``.  ``realtime`` = ``RealtimeReport.as_dict()`` of
    the measuring thread and ``kernel`` = ``uname -v`` only shape the advice."""
    problems: list[str] = []
    notes: list[str] = []
    if lat.samples == 0:
        problems.append("no wake-up measured")
    else:
        if lat.max_s >= budget.stale_s:
            problems.append(f"worst wake-up {_us(lat.max_s)} late >= the staleness budget "
                            f"safety.stale_ticks x period = {_us(budget.stale_s)} "
                            "(SENSOR_STALE)")
        if lat.p99_s >= budget.overrun_threshold_s:
            problems.append(f"p99 lateness {_us(lat.p99_s)} >= safety.overrun_threshold_s "
                            f"{_us(budget.overrun_threshold_s)} (routine overruns: "
                            "OVERRUN_STREAK)")
        elif lat.p9999_s >= budget.overrun_threshold_s:
            notes.append(f"p99.99 lateness {_us(lat.p9999_s)} >= safety.overrun_threshold_s "
                         f"{_us(budget.overrun_threshold_s)}: single overruns will be counted")
    if not problems:
        return Verdict(True, (), tuple(notes), ())
    return Verdict(False, tuple(problems), tuple(notes), _advice(realtime or {}, kernel))


def _advice(realtime: Mapping[str, Mapping[str, str]], kernel: str | None) -> tuple[str, ...]:
    granted = realtime.get("granted", {})
    denied = realtime.get("denied", {})
    out: list[str] = []
    if "sched_fifo" in denied:
        out.append(f"SCHED_FIFO was refused ({denied['sched_fifo']}): run under "
                   "deploy/rig.service (LimitRTPRIO=40) or as root")
    if "mlockall" in denied:
        out.append(f"mlockall was refused ({denied['mlockall']}): LimitMEMLOCK=infinity")
    if kernel is not None and "PREEMPT_RT" not in kernel:
        out.append("boot a PREEMPT_RT kernel (Debian linux-image-rt-amd64), at least "
                   "preempt=full on a PREEMPT_DYNAMIC kernel")
    if "affinity" not in granted:
        out.append("isolate a CPU for the loop (kernel isolcpus=1 nohz_full=1 rcu_nocbs=1) "
                   "and pin it there (systemd CPUAffinity=1, or --cpu 1)")
    out.append("move IRQs off the loop's CPU except the CAN adapter's "
               "(/proc/irq/N/smp_affinity_list, irqbalance banned CPUs)")
    out.append(f"see {DOCS} (rig.service, kernel preemption, CPU idle states)")
    return tuple(out)


@dataclass(frozen=True)
class HostCheck:
    """One measurement and its judgement."""

    latency: Latency
    budget: Budget
    verdict: Verdict
    realtime: dict[str, dict[str, str]]
    seconds: float
    kernel: str

    @property
    def ok(self) -> bool:
        return self.verdict.ok

    def summary(self) -> str:
        lat = self.latency
        return (f"host check {self.seconds:g} s: lateness p50/p99/p99.99/max "
                f"{_us(lat.p50_s)}/{_us(lat.p99_s)}/{_us(lat.p9999_s)}/{_us(lat.max_s)}, "
                f"{lat.skipped} deadlines skipped; {self.verdict.line()}")

    def as_dict(self) -> dict[str, object]:
        v = self.verdict
        return {"ok": v.ok, "seconds": self.seconds, "kernel": self.kernel,
                "latency_s": self.latency.as_dict(),
                "budget_s": {"period": self.budget.period_s,
                             "stale": self.budget.stale_s,
                             "stale_ticks": self.budget.stale_ticks,
                             "overrun_threshold": self.budget.overrun_threshold_s},
                "problems": list(v.problems), "notes": list(v.notes),
                "advice": list(v.advice), "realtime": self.realtime}


def kernel_version() -> str:
    u = os.uname()
    return f"{u.release} {u.version}"


def check_host(cfg: RigConfig, seconds: float, realtime: RealtimeRequest | None = None,
               applied: RealtimeReport | None = None) -> HostCheck:
    """Measure for ``seconds`` at the configured rate in the calling thread and judge it.
    ``realtime``: apply the loop's real-time set-up to this thread first (its gc freeze
    is undone afterwards); None = measure with the thread's present set-up (``rig run``
    calls it after the loop thread's own set-up, whose report is ``applied``)."""
    report = applied if applied is not None else RealtimeReport()
    if realtime is not None:
        report = apply_realtime(realtime)
    try:
        lat = measure_wakeup(cfg.sample_time_s, seconds)
    finally:
        if realtime is not None and realtime.freeze_gc:
            restore_gc()
    budget = Budget.from_config(cfg)
    kernel = kernel_version()
    rt = report.as_dict()
    return HostCheck(lat, budget, verdict(lat, budget, realtime=rt, kernel=kernel), rt,
                     seconds, kernel)
