"""The emulated rig's CAN node (:class:`hil.node.RigNode`) on python-can's virtual bus,
tick-stepped, with the controller's end of the bus in the test's hands: ``harness()``
opens two virtual buses on a unique channel; :class:`Harness` sends valve commands and
decodes what the node sent into :class:`Rx` records.  Used by test_node.py and
test_faults.py.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import can

from controller.config import RigConfig, default_config
from hil.faults import FaultSchedule
from hil.node import RigNode
from hil.sim.roads import make_road
from rig.bus.core import make_tx_message
from rig.wire.protocol import (
    RIG_STATUS,
    ROAD_PREVIEW,
    SENSOR_DATA,
    VALVE_COMMAND,
    DecodeStatus,
    RigStatus,
    RoadPreview,
    SensorData,
)

CFG: RigConfig = default_config()


@dataclass
class Rx:
    """One frame the controller side saw, tagged with the rig tick after which it came."""

    tick: int
    frame_id: int
    data: bytes
    status: DecodeStatus = DecodeStatus.OK
    sensor: SensorData | None = None
    rig: RigStatus | None = None


@dataclass
class Harness:
    node: RigNode
    ctl: can.BusABC
    rx: list[Rx] = field(default_factory=list)
    cmd_counter: int = 0

    def __post_init__(self) -> None:
        self._msg = make_tx_message(VALVE_COMMAND.frame_id)

    def send_command(self, enable: int = 1, spool: float = 0.0, counter: int | None = None,
                     corrupt: bool = False) -> None:
        c = self.cmd_counter if counter is None else counter
        VALVE_COMMAND.encode(self._msg.data, c, enable, 1, spool, 0.0, 0)
        if corrupt:
            self._msg.data[0] ^= 0x01
        self.ctl.send(self._msg)
        if counter is None:
            self.cmd_counter = (self.cmd_counter + 1) & 0xF

    def step(self, n: int = 1,
             command: Callable[[int], dict[str, float] | None] | None = None) -> None:
        """Tick the node ``n`` times; ``command(tick)`` returns send_command kwargs or
        None (send nothing).  Frames the node sends are decoded into ``rx``."""
        for _ in range(n):
            if command is not None:
                kw = command(self.node.tick_count)
                if kw is not None:
                    self.send_command(**kw)  # type: ignore[arg-type]
            self.node.tick()
            self.drain(self.node.tick_count - 1)

    def drain(self, tick: int) -> None:
        while (msg := self.ctl.recv(timeout=0.0)) is not None:
            r = Rx(tick, msg.arbitration_id, bytes(msg.data))
            if msg.arbitration_id == SENSOR_DATA.frame_id:
                r.sensor = SensorData()
                r.status = SENSOR_DATA.decode(msg.data, r.sensor)
            elif msg.arbitration_id == RIG_STATUS.frame_id:
                r.rig = RigStatus()
                r.status = RIG_STATUS.decode(msg.data, r.rig)
            elif msg.arbitration_id == ROAD_PREVIEW.frame_id:
                r.status = ROAD_PREVIEW.decode(msg.data, RoadPreview())
            self.rx.append(r)

    def sensor_frames(self) -> list[Rx]:
        return [r for r in self.rx if r.frame_id == SENSOR_DATA.frame_id]

    def status_frames(self) -> list[Rx]:
        return [r for r in self.rx if r.frame_id == RIG_STATUS.frame_id]


@contextmanager
def harness(faults: FaultSchedule | None = None, road: str = "iso-C",
            duration_s: float = 2.0, **node_kw: object) -> Iterator[Harness]:
    channel = f"test-{uuid.uuid4().hex}"
    rig_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    ctl_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        rd = make_road(road, 11.176, duration_s, CFG.sample_time_s, seed=3)
        node = RigNode(rig_bus, CFG, rd, faults, **node_kw)  # type: ignore[arg-type]
        yield Harness(node, ctl_bus)
    finally:
        rig_bus.shutdown()
        ctl_bus.shutdown()
