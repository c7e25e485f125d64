"""The control loop on python-can's virtual bus, tick by tick, with a hand-made rig side.

``make_harness`` builds a real :class:`rig.service.loop.ControlLoop` on a fresh virtual
channel; ``RigSide`` is the rig's end of that bus (hand-made SensorData / RigStatus
frames, decodes what the controller sent).  ``FakeRuntime`` stands in for BankRuntime
where a test needs to control the bank's outputs exactly (flags, q, exceptions).
Used by test_loop.py, test_safety.py and test_lifecycle.py.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from controller.config import RigConfig, default_config
from controller.runtime.force_loop import PIForceLoop
from rig.bus.core import open_bus
from rig.service.loop import ControlLoop
from rig.wire.protocol import (
    RIG_STATUS,
    SENSOR_DATA,
    ControllerStatus,
    FaultReport,
    LifecycleState,
    ValveCommand,
)
from tests.support.frames import drain_controller_frames

PERIOD_NS = 1_000_000


class FakeRuntime:
    """BankRuntime stand-in: force reference = -gain * rattlespace; flags settable."""

    def __init__(self, n_models: int = 3, gain: float = 1e4) -> None:
        self.gain = gain
        self.weight_set = 1
        self.flags = 0
        self.q = np.full(n_models, 2.0)
        self.firing_weight = np.full(n_models, 1.0 / n_models)
        self.probability = np.full(n_models, 1.0 / n_models)
        self.u_model = np.zeros(n_models)
        self.active = np.ones(n_models, dtype=bool)
        self.x_post = np.zeros((n_models, 4))
        self.models = np.arange(n_models)
        self.running = self             # one layer: the record's columns are every model
        self.xf = np.zeros(2)
        self.stop_contact_s = 0.0
        self.comfort_share = 0.0
        self.ride_height_m = 0.0
        self.sprung_mass_est_kg = 500.0
        self.spring_rate_est_n_per_m = 27400.0
        self.damping_est_ns_per_m = 1650.0
        self.wheel_hop_hz = 9.49                # the configured rig's passive wheel hop
        self.tire_stiffness_est = 1.0
        self.preview_called = False
        self.preview_clamp_ticks = 0
        self.steps = 0
        self.resets = 0
        self.output: float | None = None      # force the output when set
        self.inputs: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def flag_bits(self) -> int:
        return int(self.flags)

    def step(self, rattlespace_m: float, accel_mps2: float, force_meas_n: float) -> float:
        self.steps += 1
        self.inputs = (rattlespace_m, accel_mps2, force_meas_n)
        return -self.gain * rattlespace_m if self.output is None else self.output

    def reset(self) -> None:
        self.resets += 1
        self.flags = 0

    def set_blending(self, b: Any) -> None:
        self.blending = int(b)

    def set_weight_set(self, w: int) -> None:
        self.weight_set = int(w)

    def set_road(self, speed_mps: float, roughness_gd: float) -> None:
        self.road = (speed_mps, roughness_gd)

    @property
    def takes_road_preview(self) -> bool:
        return self.weight_set == 0

    def use_preview_schedule(self, live: bool) -> None:
        self.preview_schedule = bool(live)

    def check_road_preview(self, preview: Any, reading_m: float, force_meas_n: float,
                           road_velocity: Any, start: int) -> bool:
        return False

    def preview_trust(self, preview: Any) -> str:
        return "inside" if self.takes_road_preview else "unused"

    def step_previewed(self, preview: Any, rattlespace_m: float, accel_mps2: float,
                       force_meas_n: float, road_velocity: Any, start: int) -> float:
        self.preview_called = self.check_road_preview(preview, rattlespace_m, force_meas_n,
                                                      road_velocity, start)
        return self.step(rattlespace_m, accel_mps2, force_meas_n)


class RigSide:
    """The rig's end of the virtual bus: sends SensorData / RigStatus, reads commands."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.sd_counter = 0
        self.rs_counter = 0
        self.valve: list[ValveCommand] = []
        self.faults: list[FaultReport] = []
        self.status: list[ControllerStatus] = []

    def sensor(self, rattlespace_m: float | None = None, force_n: float | None = None,
               accel_mps2: float | None = None, status: int = 0, counter: int | None = None,
               corrupt: bool = False) -> None:
        """Values not given: a nominal value with a one-LSB dither (cycling over 3 frames)
        so that they are never frozen (the frozen-sensor monitor would trip)."""
        buf = bytearray(8)
        c = self.sd_counter if counter is None else counter
        d = self.sd_counter % 3
        rattlespace_m = 0.001 + 5e-6 * d if rattlespace_m is None else rattlespace_m
        force_n = 10.0 + 0.5 * d if force_n is None else force_n
        accel_mps2 = 0.1 + 0.005 * d if accel_mps2 is None else accel_mps2
        SENSOR_DATA.encode(buf, c, status, rattlespace_m, force_n, accel_mps2)
        if counter is None:
            self.sd_counter += 1
        if corrupt:
            buf[3] ^= 0x01
        self.bus.send(can.Message(arbitration_id=SENSOR_DATA.frame_id, data=buf,
                                  is_extended_id=False))

    def rig_status(self, watchdog: int = 0, supply_ok: int = 1, bypass: int = 1) -> None:
        buf = bytearray(8)
        RIG_STATUS.encode(buf, self.rs_counter, bypass, watchdog, supply_ok, 10e6, 0.0, 0.0)
        self.rs_counter += 1
        self.bus.send(can.Message(arbitration_id=RIG_STATUS.frame_id, data=buf,
                                  is_extended_id=False))

    def read(self) -> tuple[list[ValveCommand], list[FaultReport]]:
        """Frames the controller sent since the last read (valve commands, fault reports)."""
        valves, faults, status = drain_controller_frames(self.bus)
        self.status.extend(status)
        self.valve.extend(valves)
        self.faults.extend(faults)
        return valves, faults


@dataclass
class LoopHarness:
    loop: ControlLoop
    rig: RigSide
    rt: Any
    buses: list[can.BusABC] = field(default_factory=list)
    t_ns: int = 0

    def step(self, *, sensor: bool = True, status: bool | None = None,
             lateness_ns: int = 0, **sensor_kw: Any) -> tuple[list[ValveCommand],
                                                               list[FaultReport]]:
        """Rig sends (optionally), controller ticks once, return what it sent."""
        if sensor:
            self.rig.sensor(**sensor_kw)
        if status is None:
            status = self.loop.tick_count % 10 == 0
        if status:
            self.rig.rig_status()
        self.loop.tick(self.t_ns, lateness_ns)
        self.t_ns += PERIOD_NS
        return self.rig.read()

    def run(self, n: int, **kw: Any) -> None:
        for _ in range(n):
            self.step(**kw)

    def capture_events(self) -> list[tuple[str, Any]]:
        """From now on, the loop's recorded events land in the returned list as
        (kind, detail) instead of in the recording."""
        events: list[tuple[str, Any]] = []
        self.loop._record_event = (  # type: ignore[method-assign]
            lambda t_ns, tick, kind, detail: events.append((kind, detail)))
        return events

    def arm(self) -> None:
        res = self.loop.request("arm", timeout_s=None)
        assert res.accepted, res.message
        assert self.loop.lifecycle.state is LifecycleState.ACTIVE

    def close(self) -> None:
        for b in self.buses:
            b.shutdown()


def make_harness(cfg: RigConfig | None = None, rt: Any = None, role: str | None = "controller",
                 **loop_kw: Any) -> LoopHarness:
    """Controller loop + rig side on a fresh virtual channel.  ``role=None`` opens the
    controller's bus without receive filters (python-can's virtual bus applies the
    filters to error frames too; SocketCAN delivers them regardless)."""
    cfg = cfg or default_config()
    channel = f"test-{uuid.uuid4().hex}"
    ctl_bus = open_bus(cfg.can, role=role, interface="virtual", channel=channel)
    rig_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    rt = rt if rt is not None else FakeRuntime()
    loop_kw.setdefault("warmup_ticks", 5)
    loop = ControlLoop(cfg, ctl_bus, rt, PIForceLoop.from_config(cfg),
                       **loop_kw)
    return LoopHarness(loop, RigSide(rig_bus), rt, [ctl_bus, rig_bus])
