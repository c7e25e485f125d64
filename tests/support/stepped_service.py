"""The service's loop stepped tick by tick against the emulated rig on a virtual bus, in
a thread (tests/test_telemetry.py, tests/test_telemetry_process.py): what reaches the loop
from the telemetry process (commands, losses) arrives as it would live, while no
real-time deadline depends on the machine's load (lateness is given, not measured)."""

from __future__ import annotations

import shutil
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from controller.config import RigConfig


class SteppedService:
    """``Service(cfg, ServiceOptions(**options))`` whose loop a thread steps against a
    ``RigNode``; ``late_ticks``: ticks to come with an overrun (5 periods late)."""

    def __init__(self, cfg: RigConfig, **options: Any) -> None:
        from controller.artifact import load_design, save_design
        from hil.node import RigNode
        from hil.sim.closed_loop import cached_design
        from hil.sim.roads import make_road
        from rig.bus.core import open_bus
        from rig.service.runner import Service, ServiceOptions

        self.cfg = cfg
        channel = f"stepped-{uuid.uuid4().hex}"
        self.rig_bus = open_bus(cfg.can, role="rig", interface="virtual", channel=channel)
        self.ctl_bus = open_bus(cfg.can, role="controller", interface="virtual",
                                channel=channel)
        self.node = RigNode(self.rig_bus, cfg,
                            make_road("rough-course", 11.176, 30.0, cfg.sample_time_s))
        self._design_dir = Path(tempfile.mkdtemp(prefix="stepped-"))
        design = self._design_dir / "design.npz"
        save_design(cached_design(cfg), design)
        load_design(design, cfg)
        opts: dict[str, Any] = {"recording": False, "telemetry": True, "realtime": None,
                                "install_signal_handlers": False, **options}
        self.svc = Service(cfg, ServiceOptions(design_path=str(design), **opts),
                           bus=self.ctl_bus)
        self.late_ticks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._step, daemon=True)
        self._thread.start()

    def _step(self) -> None:
        loop = self.svc.loop
        period = loop.period_ns
        t = time.monotonic_ns()
        while not self._stop.is_set():
            self.node.tick()
            late = 0
            if self.late_ticks:
                self.late_ticks -= 1
                late = 5 * period
            loop.tick(t, late)
            t += period
            if loop.tick_count % 20 == 0:
                time.sleep(0.001)              # let the other threads in

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.svc.close()
        self.rig_bus.shutdown()
        self.ctl_bus.shutdown()
        shutil.rmtree(self._design_dir, ignore_errors=True)
