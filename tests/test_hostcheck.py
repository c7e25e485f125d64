"""`rig check-host` and the host check of `rig run` (issue 24): the verdict on synthetic
latencies, cyclictest's histogram, the pacing measurement on a fake clock, a short real
run that checks only the structure (never timing values), and a failing required check
refusing every arm."""

from __future__ import annotations

import contextlib
import io
import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.config import ConfigError, default_config, parse_config
from rig.cli import main as rig_main
from rig.rt import cyclictest
from rig.rt.hostcheck import Budget, HostCheck, Latency, measure_wakeup, summarise, verdict
from rig.service.runner import Service, ServiceOptions

CFG = default_config()
BUDGET = Budget.from_config(CFG)          # 1 kHz, 2 ticks = 2 ms, overrun 0.5 ms
RT_KERNEL = "6.1.0-rt #1 SMP PREEMPT_RT"


def _lat(us: list[float] | np.ndarray) -> Latency:
    return summarise(np.asarray(us, dtype=np.float64) * 1e-6)


def test_budget_comes_from_the_config() -> None:
    assert BUDGET.period_s == pytest.approx(1e-3)
    assert BUDGET.stale_s == pytest.approx(CFG.safety.stale_ticks * 1e-3)
    assert BUDGET.overrun_threshold_s == CFG.safety.overrun_threshold_s
    b = Budget.from_config(CFG.replace(safety={"stale_ticks": 20}))
    assert b.stale_s == pytest.approx(0.02)


def test_summarise_percentiles() -> None:
    x = np.r_[np.full(9999, 10.0), 5000.0]
    lat = _lat(x)
    assert lat.samples == 10000
    assert lat.p50_s == pytest.approx(10e-6) and lat.p99_s == pytest.approx(10e-6)
    assert lat.max_s == pytest.approx(5e-3)
    assert lat.p9999_s > 10e-6
    assert summarise([]).samples == 0


def test_quiet_host_passes() -> None:
    rng = np.random.default_rng(1)
    v = verdict(_lat(rng.uniform(0, 50, 100_000)), BUDGET, kernel=RT_KERNEL)
    assert v.ok and not v.problems and not v.advice
    assert v.line() == "host holds the loop's timing budgets"


def test_a_stall_beyond_the_staleness_budget_fails_with_advice() -> None:
    # this kind of VM: quiet, but a 7-9 ms stall of a SCHED_FIFO thread every ~10 s
    x = np.r_[np.full(29_997, 20.0), 7000.0, 8000.0, 9000.0]
    v = verdict(_lat(x), BUDGET, kernel="6.1.0 #1 SMP PREEMPT_DYNAMIC",
                realtime={"granted": {"sched_fifo": "50"}, "denied": {}})
    assert not v.ok
    assert len(v.problems) == 1 and "safety.stale_ticks" in v.problems[0]
    assert "9000 us" in v.problems[0] and "SENSOR_STALE" in v.problems[0]
    text = " ".join(v.advice)
    for needle in ("PREEMPT_RT", "isolcpus", "CPUAffinity", "/proc/irq", "docs/deploy.md"):
        assert needle in text, needle
    assert "\n" not in v.line() and v.line().startswith("host does not hold")


def test_routine_lateness_fails_on_the_overrun_threshold() -> None:
    x = np.r_[np.full(97_000, 20.0), np.full(3000, 800.0)]       # p99 = 800 us > 500 us
    v = verdict(_lat(x), BUDGET, kernel=RT_KERNEL)
    assert not v.ok and "overrun_threshold_s" in v.problems[0]
    # rare overruns only: a note, not a failure
    y = np.r_[np.full(99_980, 20.0), np.full(20, 800.0)]
    w = verdict(_lat(y), BUDGET, kernel=RT_KERNEL)
    assert w.ok and w.notes and "p99.99" in w.notes[0]


def test_advice_follows_what_was_refused() -> None:
    x = np.r_[np.full(999, 20.0), 3000.0]
    v = verdict(_lat(x), BUDGET, kernel=RT_KERNEL,
                realtime={"granted": {"affinity": "1"},
                          "denied": {"sched_fifo": "Operation not permitted"}})
    text = " ".join(v.advice)
    assert "LimitRTPRIO" in text and "PREEMPT_RT kernel" not in text
    assert "isolcpus" not in text                               # already pinned


def test_nothing_measured_fails() -> None:
    assert not verdict(summarise([]), BUDGET).ok


def test_measure_wakeup_paces_like_the_loop_and_counts_a_stall() -> None:
    now = [0]
    wakes = [0]

    def clock() -> int:              # 1 us per read, so the final spin ends
        now[0] += 1000
        return now[0]

    def sleep(s: float) -> None:     # wakes 10 us late; the 50th time 8 ms late
        wakes[0] += 1
        now[0] += round(s * 1e9) + (8_000_000 if wakes[0] == 50 else 10_000)

    lat = measure_wakeup(1e-3, 0.2, clock=clock, sleep=sleep)
    assert 180 <= lat.samples <= 200 and lat.skipped >= 6
    assert 7e-3 < lat.max_s < 9e-3
    assert lat.p50_s < 1e-4


HIST = """# Histogram
000000 000000
000001 000010
000002 000080
000003 000009
# Total: 000000100
# Min Latencies: 00001
# Avg Latencies: 00002
# Max Latencies: 07000
# Histogram Overflows: 00001
# Histogram Overflow at cycle number:
# Thread 0: 00042
"""


def test_cyclictest_histogram_is_parsed() -> None:
    lat = cyclictest.parse_histogram(HIST)
    assert lat.samples == 100
    assert lat.p50_s == pytest.approx(2e-6) and lat.max_s == pytest.approx(7e-3)
    with pytest.raises(ValueError):
        cyclictest.parse_histogram("nothing here")


def test_cyclictest_absent_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cyclictest.shutil, "which", lambda _name: None)
    said = cyclictest.start(1.0, 1000, 50)
    assert isinstance(said, str) and "not installed" in said and "\n" not in said


def test_config_keys_are_validated_by_name() -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"safety": {"host_check_s": -1.0}})
    assert "safety.host_check_s" in str(err.value)
    with pytest.raises(ConfigError) as err:
        parse_config({"safety": {"host_check_required": "yes"}})
    assert "safety.host_check_required" in str(err.value)


def test_short_real_check_host_json_structure() -> None:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = rig_main(["check-host", "--seconds", "0.2", "--json", "--no-realtime",
                         "--no-cyclictest"])
    doc = json.loads(buf.getvalue())
    assert code == (0 if doc["ok"] else 1)              # either is fine: no timing asserted
    assert set(doc["latency_s"]) == {"samples", "p50_s", "p99_s", "p9999_s", "max_s",
                                     "skipped"}
    assert doc["latency_s"]["samples"] > 0
    assert doc["budget_s"]["stale_ticks"] == CFG.safety.stale_ticks
    assert doc["cyclictest"] is None and isinstance(doc["problems"], list)
    assert isinstance(doc["advice"], list) and bool(doc["advice"]) != doc["ok"]


def _failing_check(cfg: Any, seconds: float, realtime: Any = None, applied: Any = None
                   ) -> HostCheck:
    lat = _lat(np.r_[np.full(999, 20.0), 8000.0])
    b = Budget.from_config(cfg)
    return HostCheck(lat, b, verdict(lat, b), {}, seconds, "test")


@pytest.mark.parametrize("required", [False, True])
def test_failing_host_check_reports_and_refuses_to_arm_when_required(
        design_path: Path, monkeypatch: pytest.MonkeyPatch, required: bool) -> None:
    import rig.service.runner as runner

    monkeypatch.setattr(runner, "check_host", _failing_check)
    cfg = CFG.replace(safety={"host_check_required": required, "host_check_s": 0.1})
    opts = ServiceOptions(design_path=str(design_path), interface="virtual",
                          channel=f"hc-{uuid.uuid4().hex}", recording=False, telemetry=False,
                          realtime=None, install_signal_handlers=False, host_check=True)
    svc = Service(cfg, opts)
    said: dict[str, Any] = {}

    def operator() -> None:
        time.sleep(0.2)
        said["status"] = svc.status()["host_check"]
        try:
            svc.command_handler("arm", {})
        except ValueError as exc:            # refused (no rig on the bus, in any case)
            said["arm"] = str(exc)
        svc.stop_event.set()

    th = threading.Thread(target=operator)
    th.start()
    assert svc.run() == 0
    th.join()
    st = said["status"]
    assert st is not None and st["ok"] is False and "SENSOR_STALE" in st["problems"][0]
    if required:
        assert said["arm"].startswith("arm refused: host check failed (safety.host_check_"
                                    "required)")
        assert "\n" not in said["arm"]
    else:
        assert "host check" not in said["arm"]
