"""The control loop's seams: what :class:`rig.service.loop.ControlLoop` and
:class:`rig.service.hardware.RigIO` need of the parts plugged into them.

Structural types (``typing.Protocol``), so the service, replay, the benches and the tests
plug in the real parts or their own without inheriting anything: the controller runtime
(``controller.runtime.bank.BankRuntime``), the PI force loop
(``controller.runtime.force_loop.PIForceLoop``), the run recorder and the telemetry
process (Zenoh and the live Foxglove view).  Every call the loop makes on a recorder or
the telemetry is non-blocking: they queue and drop (and count) instead of waiting.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from rig.recording.codec import TickLayout

__all__ = ["ForceLoop", "Recorder", "RunningModels", "Runtime", "Telemetry"]


class RunningModels(Protocol):
    """The models the tick record carries (``controller.runtime.bank.RunningModels``):
    the running layer's, one column each; ``models`` is the bank's index of each column."""

    models: np.ndarray
    q: np.ndarray
    firing_weight: np.ndarray
    probability: np.ndarray
    u_model: np.ndarray
    active: np.ndarray
    x_post: np.ndarray


class Runtime(Protocol):
    """What the loop needs of ``controller.runtime.bank.BankRuntime``."""

    @property
    def flags(self) -> Any: ...
    @property
    def flag_bits(self) -> int: ...     # flags as a plain int (read every tick)
    @property
    def running(self) -> RunningModels: ...
    xf: np.ndarray
    stop_contact_s: float       # stop-contact time in the monitor's window [s]
    comfort_share: float        # the travel schedule's comfort share of the force [0, 1]
    ride_height_m: float        # mean LVDT reading about the stops' centre [m]

    @property
    def sprung_mass_est_kg(self) -> float: ...
    @property
    def spring_rate_est_n_per_m(self) -> float: ...
    @property
    def damping_est_ns_per_m(self) -> float: ...
    @property
    def wheel_hop_hz(self) -> float: ...
    @property
    def tire_stiffness_est(self) -> float: ...
    @property
    def takes_road_preview(self) -> bool: ...   # the law calls on a prediction

    def step(self, rattlespace_m: float, accel_mps2: float, force_meas_n: float) -> float: ...
    def reset(self) -> None: ...
    def set_blending(self, b: Any) -> None: ...
    def set_weight_set(self, w: int) -> None: ...
    def set_road(self, speed_mps: float, roughness_gd: float) -> Any: ...
    def use_preview_schedule(self, live: bool) -> None: ...
    def check_road_preview(self, preview: Any, reading_m: float, force_meas_n: float,
                           road_velocity: np.ndarray, start: int) -> bool: ...
    def step_previewed(self, preview: Any, rattlespace_m: float, accel_mps2: float,
                       force_meas_n: float, road_velocity: np.ndarray, start: int
                       ) -> float: ...              # check_road_preview, then step
    @property
    def preview_called(self) -> bool: ...           # ... and its check called the law
    @property
    def preview_clamp_ticks(self) -> int: ...       # ticks the stop clamp clipped the force
    def preview_trust(self, preview: Any) -> str: ...   # how far the prediction is trusted


class ForceLoop(Protocol):
    """``controller.runtime.force_loop.PIForceLoop`` (the force inner loop) as the loop uses it."""

    def step(self, force_ref_n: float, force_meas_n: float, rattlespace_m: float
             ) -> float: ...
    def reset(self) -> None: ...


class Recorder(Protocol):
    """``rig.recording.recorder.RunRecorder`` as the loop uses it (all calls non-blocking)."""

    @property
    def dropped(self) -> int: ...
    def can_frame(self, t_ns: int, tick: int, arbitration_id: int,
                  data: bytes | bytearray | memoryview,
                  is_rx: bool, error_frame: bool = False, extended_id: bool = False
                  ) -> bool: ...
    def set_tick_layout(self, layout: TickLayout) -> None: ...
    def tick_packed(self, record: bytes | bytearray | memoryview) -> bool: ...
    def event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool: ...


class Telemetry(Protocol):
    """``rig.telemetry_process.link.TelemetryLink`` (the telemetry process) as the loop
    uses it: every call is the loop thread's and never blocks."""

    @property
    def dropped(self) -> int: ...
    @property
    def tick_every(self) -> int: ...
    def offer_packed(self, record: bytes | bytearray | memoryview) -> bool: ...
    def offer_event(self, t_ns: int, tick: int, kind: str, detail: Any) -> bool: ...
    def poll(self, loop: Any) -> None: ...
