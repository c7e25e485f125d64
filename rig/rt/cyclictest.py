"""``cyclictest`` (Debian package rt-tests) run next to ``rig check-host``.

:func:`start` launches it for the same duration, interval, SCHED_FIFO priority and CPUs
as the measurement (``-m -q -t 1 -h``: one thread, memory locked, a latency histogram in
1 us buckets written to a file); :meth:`CyclictestRun.finish` waits and parses the
histogram (:func:`parse_histogram`, pure) into a :class:`rig.rt.hostcheck.Latency`.
Absent, refused (no privileges) or failing, it is one line saying so (a ``str`` instead
of the figures).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.rt.hostcheck import Latency, summarise

__all__ = ["CyclictestRun", "parse_histogram", "start"]

_BUCKET = re.compile(r"^(\d+)\s+(\d+)")
_FIELD = re.compile(r"^#\s*(Max Latencies|Histogram Overflows|Total):\s*(\d+)")


def parse_histogram(text: str) -> Latency:
    """``Latency`` of thread 0 from cyclictest's ``-h`` output (buckets of 1 us; the
    overflows counted at the reported maximum)."""
    us: list[int] = []
    counts: list[int] = []
    fields: dict[str, int] = {}
    for line in text.splitlines():
        m = _BUCKET.match(line)
        if m:
            us.append(int(m.group(1)))
            counts.append(int(m.group(2)))
            continue
        f = _FIELD.match(line)
        if f:
            fields[f.group(1)] = int(f.group(2))
    if not us and "Max Latencies" not in fields:
        raise ValueError("no histogram in cyclictest's output")
    values = np.repeat(np.asarray(us, dtype=np.float64), np.asarray(counts, dtype=np.int64))
    over = fields.get("Histogram Overflows", 0)
    worst = float(fields.get("Max Latencies", values.max() if values.size else 0.0))
    if over:
        values = np.concatenate([values, np.full(over, worst)])
    lat = summarise(values * 1e-6)
    return Latency(lat.samples, lat.p50_s, lat.p99_s, lat.p9999_s, worst * 1e-6)


@dataclass
class CyclictestRun:
    proc: subprocess.Popen[str]
    histfile: Path
    timeout_s: float

    def finish(self) -> Latency | str:
        """The figures, or one line saying why there are none."""
        try:
            _, err = self.proc.communicate(timeout=self.timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            return "cyclictest: did not finish in time (killed)"
        try:
            if self.proc.returncode != 0:
                last = next((ln.strip() for ln in reversed(err.splitlines()) if ln.strip()),
                            "no message")
                return (f"cyclictest: failed (exit {self.proc.returncode}: {last}; it needs "
                        "root or RLIMIT_RTPRIO / RLIMIT_MEMLOCK)")
            try:
                return parse_histogram(self.histfile.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                return f"cyclictest: no figures ({exc})"
        finally:
            self.histfile.unlink(missing_ok=True)


def start(seconds: float, interval_us: int, priority: int, cpus: tuple[int, ...] = (),
          histogram_us: int = 20000) -> CyclictestRun | str:
    """Start cyclictest (not waiting); one line instead when it cannot run."""
    exe = shutil.which("cyclictest")
    if exe is None:
        return ("cyclictest: not installed (Debian package rt-tests: "
                "scripts/ensure-debian-packages.sh rt-tests)")
    fd, name = tempfile.mkstemp(prefix="rig-cyclictest-", suffix=".txt")
    os.close(fd)
    cmd = [exe, "-m", "-q", "-t", "1", f"-i{max(1, interval_us)}",
           f"-D{max(1, round(seconds))}", f"-h{histogram_us}", f"--histfile={name}"]
    if priority > 0:
        cmd.append(f"-p{priority}")
    if cpus:
        cmd.append(f"-a{','.join(str(c) for c in sorted(cpus))}")
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
    except OSError as exc:
        Path(name).unlink(missing_ok=True)
        return f"cyclictest: cannot start ({exc.strerror or exc})"
    return CyclictestRun(proc, Path(name), timeout_s=seconds + 30.0)
