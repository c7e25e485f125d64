"""Helpers for the real-SocketCAN suite: process management, captures, E2E protection.

Everything here is independent of the project's own codec (``rig.wire.protocol``) on purpose:
the suite checks the service's frames against this second implementation and cantools.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PYTHON = sys.executable
DBC_PATH = REPO / "rig" / "wire" / "rig.dbc"
CHANNEL = os.environ.get("SOCKETCAN_CHANNEL", "vcan0")


#: name -> (value, unit, note): measurements the tests make, printed at the end of the run
MEASUREMENTS: dict[str, tuple[float, str, str]] = {}


def record(name: str, value: float, unit: str, note: str = "") -> None:
    """Keep a measurement for the end-of-run table (and print it at once)."""
    MEASUREMENTS[name] = (float(value), unit, note)
    print(f"measured {name}: {value:.6g} {unit} {note}".rstrip())


def vcan_status(channel: str) -> tuple[bool, str]:
    """(usable, reason): ``channel`` exists, is up and a raw CAN socket can bind to it."""
    if not hasattr(socket, "AF_CAN"):
        return False, "this Python has no AF_CAN"
    if not Path(f"/sys/class/net/{channel}").exists():
        return False, f"no {channel} network interface (run tests/socketcan/run.sh)"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as s:
            s.bind((channel,))
    except OSError as exc:
        return False, f"cannot bind a CAN_RAW socket to {channel}: {exc}"
    flags = Path(f"/sys/class/net/{channel}/flags").read_text().strip()
    if not int(flags, 16) & 0x1:  # IFF_UP
        return False, f"{channel} is down"
    return True, ""


# --------------------------------------------------------------------- E2E protection
def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8 SAE J1850: poly 0x1D, init 0xFF, xor-out 0xFF, no reflection (bitwise)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def frame_crc(frame_id: int, data: bytes) -> int:
    """The DBC's byte-0 CRC: over [id & 0xFF, id >> 8] + bytes 1..7."""
    return crc8_sae_j1850(bytes([frame_id & 0xFF, (frame_id >> 8) & 0xFF]) + bytes(data[1:8]))


def protect(frame_id: int, data: bytes | bytearray, counter: int) -> bytes:
    """Set the rolling counter (byte 1 low nibble) and the CRC (byte 0) of an 8-byte frame."""
    out = bytearray(data)
    out[1] = (out[1] & 0xF0) | (counter & 0x0F)
    out[0] = frame_crc(frame_id, bytes(out))
    return bytes(out)


# ------------------------------------------------------------------- candump captures
_LOG_LINE = re.compile(r"^\((?P<t>\d+\.\d+)\)\s+(?P<ch>\S+)\s+(?P<id>[0-9A-Fa-f]+)#(?P<data>\S*)")


@dataclass(frozen=True)
class CapturedFrame:
    timestamp_s: float
    channel: str
    arbitration_id: int
    data: bytes


def read_candump_log(path: Path) -> list[CapturedFrame]:
    """Parse a candump ``-L`` / python-can ``.log`` file (classic data frames only)."""
    frames = []
    for line in Path(path).read_text().splitlines():
        m = _LOG_LINE.match(line.strip())
        if m is None:
            continue
        data = m["data"]
        if data.startswith("R"):  # remote frame
            continue
        frames.append(CapturedFrame(float(m["t"]), m["ch"], int(m["id"], 16),
                                    bytes.fromhex(data)))
    return frames


def counter_gaps(frames: Sequence[CapturedFrame], frame_id: int) -> tuple[int, int, int]:
    """(frames, lost, duplicated) of ``frame_id``'s rolling counter (byte 1 low nibble).

    A step of 1 (mod 16) is normal; a step of 0 is a duplicate; a step of k > 1 means
    k - 1 frames lost (gaps of >= 16 frames are not detectable from a 4-bit counter; the
    tick-rate checks catch those).
    """
    counters = [f.data[1] & 0x0F for f in frames if f.arbitration_id == frame_id]
    lost = dup = 0
    for a, b in itertools.pairwise(counters):
        step = (b - a) % 16
        if step == 0:
            dup += 1
        elif step > 1:
            lost += step - 1
    return len(counters), lost, dup


# ------------------------------------------------------------------ child processes
def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Child:
    """A child process in its own session; output goes to ``log_path``."""

    def __init__(self, name: str, argv: Sequence[str], log_path: Path,
                 cwd: Path = REPO, env: dict[str, str] | None = None) -> None:
        self.name = name
        self.argv = list(argv)
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in stop()
        full_env = dict(os.environ, PYTHONUNBUFFERED="1")
        full_env.update(env or {})
        self.proc = subprocess.Popen(self.argv, cwd=cwd, env=full_env, stdout=self._log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_for_output(self, pattern: str, timeout_s: float) -> re.Match[str]:
        """Wait until the output matches ``pattern`` (regex); raise with the output if not."""
        deadline = time.monotonic() + timeout_s
        rx = re.compile(pattern, re.MULTILINE)
        while True:
            m = rx.search(self.output())
            if m is not None:
                return m
            if self.proc.poll() is not None:
                raise AssertionError(f"{self.name} exited ({self.proc.returncode}) before "
                                     f"printing /{pattern}/:\n{self.output()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name}: no /{pattern}/ within {timeout_s} s:\n"
                                     f"{self.output()}")
            time.sleep(0.05)

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired as exc:
            raise AssertionError(f"{self.name} did not exit within {timeout_s} s:\n"
                                 f"{self.output()}") from exc

    def stop(self, sig: int = signal.SIGINT, grace_s: float = 5.0) -> int:
        """Signal the child (by PID), escalate to SIGKILL after ``grace_s``; exit status."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5.0)
        self._log.close()
        return int(self.proc.returncode)


class Children:
    """Starts children and stops every one of them (by PID) at teardown."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.children: list[Child] = []

    def start(self, name: str, argv: Sequence[str], **kwargs: object) -> Child:
        child = Child(name, argv, self.log_dir / f"{name}.log", **kwargs)  # type: ignore[arg-type]
        self.children.append(child)
        return child

    def python(self, name: str, *args: str, **kwargs: object) -> Child:
        return self.start(name, [PYTHON, *args], **kwargs)

    def stop_all(self) -> None:
        for child in reversed(self.children):
            child.stop()

    def dump(self) -> Iterator[str]:
        for child in self.children:
            yield f"----- {child.name} (pid {child.pid}, {' '.join(child.argv)}) -----"
            yield child.output()[-4000:]
