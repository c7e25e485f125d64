"""Fault monitors of the control loop, allocation-free per tick.

The loop feeds the monitor the facts of each tick in order and reads back the first
fault condition observed (``code``, ``detail``).  The monitor decides nothing about the
valve: the loop latches the lifecycle FAULT and sends the safe command in the same tick.

Per tick::

    mon.begin_tick()
    mon.sensor_frame(crc_ok, counter, status_bits, rattlespace_m, force_n, accel_mps2)  # 0..n
    mon.rig_status(crc_ok, counter, watchdog_tripped, supply_ok)                        # 0..n
    mon.bus_error(FaultCode.BUS_ERROR, detail)                                          # 0..n
    mon.end_receive()            # stale check
    mon.estimator(flags, force_ref_n) ; mon.overrun(streak) ; mon.exception()
    if mon.code: ...             # FaultCode of the first condition seen this tick

``condition`` is the code of the last completed tick.  A reset is refused while
:meth:`FaultMonitor.reset_blocker` is not NONE: the last tick's condition, or the rig's
state as its *last* RigStatus reported it (supply loss is sticky between the 100 Hz
RigStatus frames), or a RigStatus missing / stale for more than
``safety.rig_status_stale_ticks`` ticks.  ``detail`` byte per code is tabulated in
docs/service.md.

Frozen sensor: a rattlespace, force or acceleration raw value bit-identical in more than
``safety.frozen_ticks`` consecutive SensorData frames (the counter still advancing)
raises SENSOR_FROZEN (detail = which signal).  The real sensors' noise (LVDT, load cell
and accelerometer each ~10 quantisation steps std) makes 51 identical readings in a row
practically impossible (< 1e-50).
"""

from __future__ import annotations

import math

import numpy as np

from controller.config import RigConfig
from rig.wire.e2e import CounterMonitor, CounterStatus
from rig.wire.protocol import FaultCode

__all__ = [
    "DETAIL_ACCEL",
    "DETAIL_ESTIMATOR",
    "DETAIL_FORCE",
    "DETAIL_OUTPUT",
    "DETAIL_RATTLESPACE",
    "DETAIL_RECV",
    "DETAIL_RIG_STATUS",
    "DETAIL_RIG_STATUS_STALE",
    "DETAIL_SEND",
    "DETAIL_SENSOR_DATA",
    "FaultMonitor",
]

# detail bytes (FaultReport.FaultDetail)
DETAIL_SENSOR_DATA = 1      # SENSOR_CRC / SENSOR_COUNTER: which frame
DETAIL_RIG_STATUS = 2
DETAIL_RATTLESPACE = 1      # SENSOR_RANGE / NONFINITE: which signal
DETAIL_FORCE = 2
DETAIL_ACCEL = 3
DETAIL_ESTIMATOR = 4        # NONFINITE from the bank (StepFlag NONFINITE_*)
DETAIL_OUTPUT = 5           # NONFINITE force reference or spool command
DETAIL_SEND = 1             # BUS_ERROR: exception from send
DETAIL_RECV = 2             # BUS_ERROR: exception from recv
DETAIL_RIG_STATUS_STALE = 3  # reset/arm refusal only: RigStatus missing or stale

_STEP_NONFINITE = 1 | 2     # StepFlag.NONFINITE_INPUT | NONFINITE_STATE
_STEP_DIVERGED = 8          # StepFlag.DIVERGED: the bank's monitor found the estimate unusable

_NONE = FaultCode.NONE


class FaultMonitor:
    """All per-tick fault checks of the service (see module docstring)."""

    def __init__(self, cfg: RigConfig) -> None:
        s, sa = cfg.sensors, cfg.safety
        self.rattlespace_limit_m = s.lvdt_range_m
        self.force_limit_n = min(s.load_cell_range_n, sa.force_range_n)
        self.accel_limit_mps2 = s.accel_range_mps2
        self.stale_ticks = sa.stale_ticks
        self.overrun_streak_limit = sa.overrun_streak
        self.frozen_ticks = sa.frozen_ticks
        self.rig_status_stale_ticks = sa.rig_status_stale_ticks
        self.sensor_counter = CounterMonitor()
        self.status_counter = CounterMonitor()
        # the rig holds WatchdogTripped until it is re-enabled (Enable=1), so the fault is
        # its rising edge; this memory survives reset() (else a reset would re-trigger it)
        self.rig_watchdog_seen = False
        self.reset()

    def reset_estimator_checks(self) -> None:
        """After an operator reset (the estimator restarts).  The estimator's own
        statistics restart with the bank (``rt.reset()``, controller/monitor.py); the
        facts about the bus (last frame, counters, age) carry on."""

    def reset(self) -> None:
        """Forget all history (start-up)."""
        self.sensor_counter.reset()
        self.status_counter.reset()
        self.code = _NONE
        self.detail = 0
        self.condition = _NONE
        self.condition_detail = 0
        self.sensor_seen = False
        self.sensor_age_ticks = 0       # ticks since the last valid SensorData
        self.fresh = False              # a valid SensorData arrived this tick
        self.counts = np.zeros(256, dtype=np.int64)   # conditions seen, per FaultCode
        # frozen-sensor monitor: last accepted values and how often each repeated
        self.last_rattlespace_m = math.nan
        self.last_force_n = math.nan
        self.last_accel_mps2 = math.nan
        self.frozen_rattlespace = 0
        self.frozen_force = 0
        self.frozen_accel = 0
        # the rig's state as the last RigStatus (valid CRC) reported it: sticky until the
        # next one (RigStatus comes at 100 Hz, the loop runs at 1 kHz)
        self.rig_status_seen = False
        self.rig_status_age_ticks = 0
        self.rig_status_fresh = False
        self.rig_supply_ok = True

    # ------------------------------------------------------------------ per tick
    def begin_tick(self) -> None:
        self.code = _NONE
        self.detail = 0
        self.fresh = False
        self.rig_status_fresh = False

    def _flag(self, code: FaultCode, detail: int) -> None:
        self.counts[code] += 1
        if self.code is _NONE:
            self.code = code
            self.detail = detail if detail < 255 else 255

    def sensor_frame(self, crc_ok: bool, counter: int, status_bits: int, rattlespace_m: float,
                     force_n: float, accel_mps2: float) -> bool:
        """Check one SensorData frame; True if its values may be used."""
        if not crc_ok:
            self._flag(FaultCode.SENSOR_CRC, DETAIL_SENSOR_DATA)
            return False
        st = self.sensor_counter.check(counter)
        if st is CounterStatus.REPEATED or st is CounterStatus.JUMPED:
            self._flag(FaultCode.SENSOR_COUNTER, DETAIL_SENSOR_DATA)
            return False
        usable = True
        if status_bits:
            self._flag(FaultCode.SENSOR_STATUS, status_bits)
            usable = False
        lim = self.rattlespace_limit_m
        if not -lim <= rattlespace_m <= lim:
            self._range(rattlespace_m, DETAIL_RATTLESPACE)
            usable = False
        lim = self.force_limit_n
        if not -lim <= force_n <= lim:
            self._range(force_n, DETAIL_FORCE)
            usable = False
        lim = self.accel_limit_mps2
        if not -lim <= accel_mps2 <= lim:
            self._range(accel_mps2, DETAIL_ACCEL)
            usable = False
        if usable:
            self._frozen(rattlespace_m, force_n, accel_mps2)
            self.fresh = True
            self.sensor_seen = True
            self.sensor_age_ticks = 0
        return usable

    def _frozen(self, rattlespace_m: float, force_n: float, accel_mps2: float) -> None:
        """Count repeats of bit-identical values per signal (decoding is injective, so
        equal floats are equal raw values); SENSOR_FROZEN once a value was the same in
        more than ``frozen_ticks`` consecutive frames (``frozen_ticks`` repeats)."""
        # written out per signal: this runs for every good frame, and a loop or a helper
        # call per signal costs more than the check itself
        lim = self.frozen_ticks
        if rattlespace_m == self.last_rattlespace_m:
            self.frozen_rattlespace += 1
            if self.frozen_rattlespace >= lim:
                self._flag(FaultCode.SENSOR_FROZEN, DETAIL_RATTLESPACE)
        else:
            self.frozen_rattlespace = 0
            self.last_rattlespace_m = rattlespace_m
        if force_n == self.last_force_n:
            self.frozen_force += 1
            if self.frozen_force >= lim:
                self._flag(FaultCode.SENSOR_FROZEN, DETAIL_FORCE)
        else:
            self.frozen_force = 0
            self.last_force_n = force_n
        if accel_mps2 == self.last_accel_mps2:
            self.frozen_accel += 1
            if self.frozen_accel >= lim:
                self._flag(FaultCode.SENSOR_FROZEN, DETAIL_ACCEL)
        else:
            self.frozen_accel = 0
            self.last_accel_mps2 = accel_mps2

    def _range(self, value: float, which: int) -> None:
        if math.isfinite(value):
            self._flag(FaultCode.SENSOR_RANGE, which)
        else:
            self._flag(FaultCode.NONFINITE, which)

    def rig_status(self, crc_ok: bool, counter: int, watchdog_tripped: bool,
                   supply_ok: bool) -> None:
        if not crc_ok:
            self._flag(FaultCode.SENSOR_CRC, DETAIL_RIG_STATUS)
            return
        self.rig_status_seen = True
        self.rig_status_fresh = True
        self.rig_status_age_ticks = 0
        self.rig_supply_ok = supply_ok
        st = self.status_counter.check(counter)
        if st is CounterStatus.REPEATED or st is CounterStatus.JUMPED:
            self._flag(FaultCode.SENSOR_COUNTER, DETAIL_RIG_STATUS)
        if watchdog_tripped and not self.rig_watchdog_seen:
            self._flag(FaultCode.RIG_WATCHDOG, 0)
        self.rig_watchdog_seen = watchdog_tripped
        if not supply_ok:
            self._flag(FaultCode.SUPPLY_LOSS, 0)

    def bus_error(self, code: FaultCode, detail: int) -> None:
        self._flag(code, detail)

    def end_receive(self) -> None:
        """After the drain: age the sensor data and check staleness."""
        if not self.rig_status_fresh:
            self.rig_status_age_ticks += 1
        if not self.fresh:
            self.sensor_age_ticks += 1
            if self.sensor_seen and self.sensor_age_ticks > self.stale_ticks:
                self._flag(FaultCode.SENSOR_STALE, self.sensor_age_ticks)

    def estimator(self, flags: int, force_ref_n: float) -> None:
        """Bank step outcome: StepFlag bits and the output.  NONFINITE_* and DIVERGED (the
        bank's monitor found the estimate unusable: controller/monitor.py) are faults;
        DEGRADED is not (the bank runs its conservative law and re-arms by itself)."""
        if flags & _STEP_NONFINITE:
            self._flag(FaultCode.NONFINITE, DETAIL_ESTIMATOR)
        elif not math.isfinite(force_ref_n):
            self._flag(FaultCode.NONFINITE, DETAIL_OUTPUT)
        if flags & _STEP_DIVERGED:
            self._flag(FaultCode.ESTIMATOR_DIVERGED, 0)

    def output(self, spool: float) -> None:
        if not math.isfinite(spool):
            self._flag(FaultCode.NONFINITE, DETAIL_OUTPUT)

    def overrun(self, streak: int) -> None:
        if streak >= self.overrun_streak_limit:
            self._flag(FaultCode.OVERRUN_STREAK, streak)

    def exception(self) -> None:
        self._flag(FaultCode.EXCEPTION, 0)

    def end_tick(self) -> None:
        """The tick's first condition becomes :attr:`condition` (what reset looks at)."""
        self.condition = self.code
        self.condition_detail = self.detail

    # ------------------------------------------------------------------ health
    @property
    def sensors_healthy(self) -> bool:
        return (self.sensor_seen and self.sensor_age_ticks <= self.stale_ticks
                and self.condition is _NONE and self.rig_problem() == "")

    def rig_problem(self) -> str:
        """Why the rig's last reported state forbids arm/reset ('' if it does not)."""
        if not self.rig_status_seen:
            return "no valid RigStatus received yet"
        if self.rig_status_age_ticks > self.rig_status_stale_ticks:
            return f"RigStatus stale for {self.rig_status_age_ticks} ticks"
        if not self.rig_supply_ok:
            return "rig reports hydraulic supply loss"
        return ""

    def reset_blocker(self) -> FaultCode:
        """The condition a reset must wait for (NONE: reset allowed).  Besides the last
        tick's condition, the rig's sticky last-reported supply state and a missing or
        stale RigStatus block it.  The rig watchdog is an event (its rising edge): the
        rig holds the flag until re-enabled by arming, so it does not block reset."""
        if self.condition is not _NONE:
            return self.condition
        if not self.rig_status_seen or self.rig_status_age_ticks > self.rig_status_stale_ticks:
            return FaultCode.SENSOR_STALE
        if not self.rig_supply_ok:
            return FaultCode.SUPPLY_LOSS
        return _NONE

    def health_problem(self) -> str:
        """Why the sensors are not healthy ('' if they are); off the hot path."""
        if not self.sensor_seen:
            return "no valid SensorData received yet"
        if self.sensor_age_ticks > self.stale_ticks:
            return f"SensorData stale for {self.sensor_age_ticks} ticks"
        if self.condition is not _NONE:
            return f"fault condition {self.condition.name} present"
        return self.rig_problem()
