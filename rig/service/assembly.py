"""How a run's control loop is built: one recipe for the service and for replay.

:class:`LoopSettings` are the construction choices beyond the configuration (controller
mode, weight set, arming warm-up, single model, identification excitation).  The service
writes them into the recording's metadata with :meth:`LoopSettings.metadata`; replay
reads them back with :meth:`LoopSettings.from_metadata` and builds the same loop with
:func:`build_control_loop`.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import can

from controller.artifact import Design
from controller.config import RigConfig
from controller.runtime.bank import BankRuntime
from controller.runtime.force_loop import PIForceLoop
from rig.rt.sdnotify import SdNotifier
from rig.service.loop import ControlLoop
from rig.service.seams import Recorder

__all__ = ["LoopSettings", "build_control_loop"]

#: recording metadata keys of the settings (values JSON-encoded by the recorder)
_KEYS = ("blending", "weight_set", "warmup_ticks", "single_model", "excitation")


@dataclass(frozen=True)
class LoopSettings:
    """Construction choices of a run's loop and bank beyond the configuration."""

    blending: int                   #: controller mode (wire value, controller.modes)
    weight_set: int                 #: LQ weight set of the design (1-based)
    warmup_ticks: int | None = None  #: good-data ticks before arming (None: from config)
    single_model: int | None = None  #: the LQG mode's model (None: the default one)
    excite: bool = False            #: the identification excitation is played

    def metadata(self) -> dict[str, Any]:
        """The recording metadata that records these settings."""
        return {"blending": self.blending, "weight_set": self.weight_set,
                "warmup_ticks": self.warmup_ticks, "single_model": self.single_model,
                "excitation": self.excite}

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str], first_record: Mapping[str, Any],
                      cfg: RigConfig, excitation_played: bool = False) -> LoopSettings:
        """The settings a recording was made with: its metadata (:meth:`metadata`);
        mode and weight set of a recording made without them from its first tick
        record, else the configuration's defaults.  ``excitation_played``: the recording
        has ``excitation`` events (the mark of an identification run, docs/identify.md)."""
        meta: dict[str, Any] = {}
        for key in _KEYS:
            if key in metadata:
                with contextlib.suppress(json.JSONDecodeError, TypeError):
                    meta[key] = json.loads(metadata[key])
        blending = meta.get("blending", first_record.get("blending", 0))
        weight_set = meta.get("weight_set", first_record.get("weight_set",
                                                             cfg.design.weight_set))
        warmup = meta.get("warmup_ticks")
        single = meta.get("single_model")
        return cls(int(blending), int(weight_set),
                   None if warmup is None else int(warmup),
                   None if single is None else int(single),
                   bool(meta.get("excitation")) or excitation_played)


def build_control_loop(cfg: RigConfig, design: Design, bus: can.BusABC,
                       settings: LoopSettings, *, recorder: Recorder | None = None,
                       notifier: SdNotifier | None = None,
                       clock_ns: Callable[[], int] = time.monotonic_ns,
                       timing_ring: int = 1 << 16) -> ControlLoop:
    """The control loop of ``settings`` on ``bus``: bank runtime, PI force loop and (for an
    identification run) the excitation's force reference."""
    runtime = BankRuntime(design, blending=settings.blending, weight_set=settings.weight_set,
                          single_model=settings.single_model, cfg=cfg)
    excitation = None
    if settings.excite:
        from controller.excitation import excitation_force

        excitation = excitation_force(cfg)
    return ControlLoop(cfg, bus, runtime, PIForceLoop.from_config(cfg), recorder=recorder,
                       notifier=notifier, blending=settings.blending,
                       weight_set=settings.weight_set, clock_ns=clock_ns,
                       warmup_ticks=settings.warmup_ticks, timing_ring=timing_ring,
                       excitation=excitation)
