"""The road ahead from the rig's RoadPreview frames, aligned to its SensorData frames.

A rig that knows the road it is about to play sends, every tick right after SensorData,
a RoadPreview frame (``rig/wire/rig.dbc``): the road velocity it plays ``PreviewLead``
ticks after the tick of the SensorData frame whose rolling counter is
``PreviewSensorCounter``.  :class:`RoadPreviewStream` turns those frames into the window
the road preview's prediction takes (``BankRuntime.check_road_preview``): the road
velocity of the ``horizon`` rig ticks after the tick of the latest accepted SensorData
frame, the ones the command computed from it can still act on.

Rig ticks are counted from the SensorData frames: each accepted frame advances the count
by its rolling counter's step (a lost frame counts, up to 15 in a row; a longer silence
is a SENSOR_STALE fault long before).  A RoadPreview frame names its SensorData frame by
counter: up to 7 ticks after the latest accepted one (when that frame was lost) or up to
8 before it.  A preview sample lands at its rig tick in a ring
of ``capacity`` ticks written twice (index i and i + capacity), so every window is one
contiguous slice ``ring[start:start + horizon]`` and the prediction reads it in place.
The samples received form one run of consecutive rig ticks; a sample that does not
follow the run (a lost or corrupt frame, a changed lead) starts a new one.  The window is
*live* when the run covers it; otherwise the schedule runs on the reading alone and
:meth:`RoadPreviewStream.why_not_live` says why.  Nothing here allocates after
construction, and nothing raises on bad input: a frame that is not usable only ends the
run.
"""

from __future__ import annotations

import numpy as np

from rig.wire.protocol import PreviewStatus

__all__ = ["RoadPreviewStream"]

_NO_ROAD = int(PreviewStatus.NO_ROAD)


class RoadPreviewStream:
    """Road velocity ahead [m/s] by rig tick, from RoadPreview frames.

    ``horizon``: the window's length in ticks (the predictor's ``horizon_ticks``);
    ``capacity``: the ring's length in ticks, a power of two at least the largest usable
    lead plus the horizon (a larger lead is refused: ``lost_reason`` ``"lead"``)."""

    def __init__(self, horizon: int, capacity: int = 4096) -> None:
        if horizon < 1:
            raise ValueError(f"road preview horizon {horizon} ticks: at least 1")
        if capacity & (capacity - 1) or capacity < 2 * horizon:
            raise ValueError(f"road preview ring of {capacity} ticks: a power of two of at "
                             f"least twice the horizon ({2 * horizon})")
        self.horizon = horizon
        self.capacity = capacity
        self.max_lead = capacity - horizon - 16     # a sample lands before it is needed
        self.ring = np.zeros(2 * capacity)
        self.reset()

    def reset(self) -> None:
        """No rig tick seen, no preview."""
        self.rig_tick = -1              # rig tick of the latest accepted SensorData
        self._sensor_counter = 0
        self.run_start = 0              # the run of consecutive samples: rig ticks
        self.run_end = -1               # run_start .. run_end (empty while end < start)
        self.lead = -1
        self.breaks = 0                 # runs ended by a frame that did not follow
        self.lost_reason = "no_frame"   # why the run ended (or none began)

    # ------------------------------------------------------------------ input
    def sensor(self, counter: int) -> None:
        """An accepted SensorData frame with rolling counter ``counter`` (0..15)."""
        if self.rig_tick < 0:
            self.rig_tick = 0
        else:
            self.rig_tick += (counter - self._sensor_counter) & 15
        self._sensor_counter = counter

    def frame(self, good: bool, status: int, velocity_mps: float, lead: int,
              sensor_counter: int) -> None:
        """A RoadPreview frame: ``good`` false for one whose CRC or length failed (its
        fields are then not read)."""
        if not good:
            self._break("corrupt")
            return
        if status & _NO_ROAD:
            self._break("no_road")
            return
        if self.rig_tick < 0:
            self._break("no_sensor")
            return
        if not self.horizon <= lead <= self.max_lead:
            self._break("lead")
            return
        if velocity_mps != velocity_mps:
            self._break("corrupt")
            return
        # the SensorData frame it names: up to 7 ahead of the latest accepted one (that
        # frame was lost or rejected), else up to 8 behind (a frame that came late)
        d = (sensor_counter - self._sensor_counter) & 15
        t = self.rig_tick + (d if d < 8 else d - 16) + lead
        if lead != self.lead:
            self.lead = lead
            self._start(t)
        elif self.run_end >= self.run_start and t == self.run_end + 1:
            self.run_end = t
        elif self.run_end >= self.run_start and t <= self.run_end:
            return                      # a repeat of a sample held: keep the run
        else:
            if self.run_end >= self.run_start:
                self.breaks += 1
            self._start(t)
        i = t & (self.capacity - 1)
        self.ring[i] = velocity_mps
        self.ring[i + self.capacity] = velocity_mps

    def _start(self, t: int) -> None:
        self.run_start = t
        self.run_end = t

    def _break(self, reason: str) -> None:
        if self.run_end >= self.run_start:
            self.breaks += 1
        self.run_start, self.run_end = 0, -1
        self.lead = -1
        self.lost_reason = reason

    # ------------------------------------------------------------------ output
    def window_start(self) -> int:
        """Index into :attr:`ring` of the window (the road velocity of the ``horizon``
        rig ticks after the latest SensorData's), or -1 when it is not live."""
        first = self.rig_tick + 1
        if self.rig_tick < 0 or first < self.run_start or first + self.horizon - 1 > self.run_end:
            return -1
        return first & (self.capacity - 1)

    def why_not_live(self) -> str:
        """Why :meth:`window_start` is -1 (``"live"`` when it is not): ``no_frame``,
        ``corrupt``, ``no_road`` (the rig says it plays no known road), ``no_sensor``,
        ``lead`` (outside horizon .. max_lead), ``filling`` (a run began and does not
        reach back to now yet), ``short`` (the samples end before the horizon: frames
        stopped or arrive too late for their lead)."""
        if self.window_start() >= 0:
            return "live"
        if self.run_end < self.run_start or self.rig_tick < 0:
            return self.lost_reason
        if self.rig_tick + 1 < self.run_start:
            return "filling"
        return "short"
