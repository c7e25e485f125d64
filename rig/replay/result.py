"""The outcome of a replay and how it is compared with the recording."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from rig.replay.recorded import RecordedRun, TxFrame
from rig.wire.protocol import VALVE_COMMAND, VALVE_COMMAND_ID, ValveCommand

__all__ = ["OPEN_LOOP_NOTE", "ReplayResult", "compare_tx", "max_abs_diff",
           "series_comparison"]

OPEN_LOOP_NOTE: Final = ("open loop: the recorded plant did not react to the replayed "
                         "commands (sensor data are the recorded ones)")


@dataclass
class ReplayResult:
    """Outcome of a replay; :meth:`summary` is what ``rig replay --json`` prints."""

    source: str
    kind: str                              # "mcap" or "log"
    same_controller: bool                  # recorded design and config
    ticks: int
    rx_frames_fed: int
    elapsed_s: float
    recorded_s: float
    complete: bool = True
    stopped_at: str | None = None
    tx_frames_recorded: int = 0
    tx_frames_replayed: int = 0
    tx_frames_compared: int = 0
    tx_frames_mismatched: int = 0
    first_mismatch: dict[str, Any] | None = None
    valve_frames_compared: int = 0
    max_abs_command_diff: float = math.nan        # spool command (normalised), per tick
    max_abs_valve_frame_spool_diff: float = math.nan
    max_abs_force_ref_diff_n: float = math.nan
    commands_reapplied: int = 0
    commands_outcome_differs: int = 0
    ticks_missing_in_recording: int = 0
    final_state: str = ""
    faults: list[str] = field(default_factory=list)       # every FAULT transition's code
    fault_ticks: list[int] = field(default_factory=list)  # ... and its tick
    bus_exceptions_recorded: int = 0   # recv / send exceptions in the recording
    bus_exceptions_raised: int = 0     # ... raised again by the replay bus
    comparison: dict[str, Any] | None = None
    out: str | None = None
    out_error: str | None = None    # why ``out`` is incomplete (a write failed), or None
    notes: list[str] = field(default_factory=list)
    # per-tick series of the replay (not in the summary)
    tick: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    spool_cmd: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    force_ref_n: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    valve_enable: NDArray[np.int8] = field(default_factory=lambda: np.zeros(0, np.int8))

    @property
    def bit_exact(self) -> bool:
        return (self.same_controller and self.tx_frames_mismatched == 0
                and self.tx_frames_compared == self.tx_frames_recorded
                and self.tx_frames_replayed == self.tx_frames_recorded
                and self.max_abs_command_diff == 0.0
                and self.max_abs_force_ref_diff_n == 0.0)

    @property
    def realtime_factor(self) -> float:
        return self.recorded_s / self.elapsed_s if self.elapsed_s > 0 else math.inf

    def summary(self) -> dict[str, Any]:
        keys = ("source", "kind", "same_controller", "ticks", "rx_frames_fed", "elapsed_s",
                "recorded_s", "complete", "stopped_at", "tx_frames_recorded",
                "tx_frames_replayed", "tx_frames_compared", "tx_frames_mismatched",
                "first_mismatch", "valve_frames_compared", "max_abs_command_diff",
                "max_abs_valve_frame_spool_diff", "max_abs_force_ref_diff_n",
                "commands_reapplied", "commands_outcome_differs",
                "ticks_missing_in_recording", "final_state", "faults", "fault_ticks",
                "bus_exceptions_recorded", "bus_exceptions_raised", "comparison",
                "out", "out_error", "notes")
        out = {k: getattr(self, k) for k in keys}
        out["bit_exact"] = self.bit_exact
        out["realtime_factor"] = self.realtime_factor
        return out


def max_abs_diff(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """max |a - b| with NaN == NaN (both non-finite in the same place counts as equal)."""
    if a.shape != b.shape:
        return math.inf
    if a.size == 0:
        return 0.0
    both_nan = np.isnan(a) & np.isnan(b)
    d = np.abs(np.where(both_nan, 0.0, a - b))
    return float(np.max(np.where(np.isnan(d), np.inf, d)))


def _frame_dict(f: TxFrame) -> dict[str, Any]:
    return {"tick": f[0], "id": f[1], "data": f[2].hex(), "flags": f[3]}


def compare_tx(rec: Sequence[TxFrame], rep: Sequence[TxFrame]
               ) -> tuple[int, int, dict[str, Any] | None, int, float]:
    """(compared, mismatched, first mismatch, ValveCommands compared, max spool diff)."""
    n = min(len(rec), len(rep))
    mismatched = 0
    first: dict[str, Any] | None = None
    valves = 0
    max_spool = 0.0
    a, b = ValveCommand(), ValveCommand()
    for i in range(n):
        r, p = rec[i], rep[i]
        if r != p:
            mismatched += 1
            if first is None:
                first = {"index": i, "recorded": _frame_dict(r), "replayed": _frame_dict(p)}
        if r[1] == VALVE_COMMAND_ID and p[1] == VALVE_COMMAND_ID:
            valves += 1
            if r[2] != p[2]:
                VALVE_COMMAND.decode(bytearray(r[2]), a)
                VALVE_COMMAND.decode(bytearray(p[2]), b)
                max_spool = max(max_spool, abs(a.spool_command - b.spool_command))
    if first is None and len(rec) != len(rep):
        i = n
        first = {"index": i, "recorded": None if i >= len(rec) else {"tick": rec[i][0]},
                 "replayed": None if i >= len(rep) else {"tick": rep[i][0]}}
    return n, mismatched, first, valves, max_spool


def series_comparison(rec: RecordedRun, spool: NDArray[np.float64],
                      fref: NDArray[np.float64], enable: NDArray[np.int8],
                      faults: list[str]) -> dict[str, Any]:
    def rms(x: NDArray[np.float64]) -> float:
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x * x))) if x.size else math.nan

    a, b = rec.force_ref_n, fref
    ok = np.isfinite(a) & np.isfinite(b)
    corr = math.nan
    if ok.sum() > 2 and np.std(a[ok]) > 0 and np.std(b[ok]) > 0:
        corr = float(np.corrcoef(a[ok], b[ok])[0, 1])
    rec_faults = [str(e["detail"].get("fault")) for e in rec.events
                  if e["kind"] == "fault" and isinstance(e["detail"], dict)]
    return {
        "note": OPEN_LOOP_NOTE,
        "force_ref_rms_recorded_n": rms(a),
        "force_ref_rms_replayed_n": rms(b),
        "force_ref_rms_difference_n": rms(a - b),
        "force_ref_correlation": corr,
        "spool_rms_recorded": rms(rec.spool_cmd),
        "spool_rms_replayed": rms(spool),
        "active_ticks_recorded": int(rec.valve_enable.sum()),
        "active_ticks_replayed": int(enable.sum()),
        "faults_recorded": rec_faults,
        "faults_replayed": faults,
    }


