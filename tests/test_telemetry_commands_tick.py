"""A command from the telemetry process takes effect in the tick it is recorded at.

``rig replay`` re-applies a recorded command before the tick its event names (as the
loop applies a command queued by :meth:`ControlLoop.request`); the loop must apply the
telemetry process's commands at that point too, or a run with a Zenoh command does not
replay bit-exact (the SocketCAN suite's service run, where the operator's listener arms
over Zenoh after a fault, failed so in one clean-clone run of three)."""

from __future__ import annotations

from typing import Any

from rig.wire.protocol import LifecycleState
from tests.support.loop_harness import make_harness


class CommandingTelemetry:
    """The loop's Telemetry seam: hands the loop one queued command per poll."""

    def __init__(self) -> None:
        self.pending: list[str] = []
        self.events: list[tuple[int, str, Any]] = []
        self.dropped = 0
        self.tick_every = 1

    def offer_packed(self, record: Any) -> bool:
        return True

    def offer_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool:
        self.events.append((tick, kind, detail))
        return True

    def poll(self, loop: Any) -> None:
        if self.pending:
            loop.request(self.pending.pop(0), None, timeout_s=None)


def test_a_telemetry_command_is_applied_before_the_step_of_its_recorded_tick() -> None:
    tel = CommandingTelemetry()
    h = make_harness(telemetry=tel)
    try:
        h.run(20)
        assert h.loop.lifecycle.state is LifecycleState.INACTIVE
        tel.pending.append("arm")
        tick = h.loop.tick_count
        valves, _ = h.step()
        commands = [(k, d) for k, kind, d in tel.events if kind == "command"]
        assert commands == [(tick, commands[0][1])] and commands[0][1]["accepted"]
        # the tick the command is recorded at already ran ACTIVE: the valve it sent is
        # enabled, as a replay that applies the command before that tick computes it
        assert h.loop.lifecycle.state is LifecycleState.ACTIVE
        assert valves and valves[-1].enable == 1
    finally:
        h.close()
