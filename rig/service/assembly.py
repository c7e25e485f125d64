"""How a run's control loop is built: one recipe for the service and for replay.

:class:`LoopSettings` are the construction choices beyond the configuration (controller
mode, weight set, arming warm-up, single model, identification excitation).  The service
writes them into the recording's metadata with :meth:`LoopSettings.metadata`; replay
reads them back with :meth:`LoopSettings.from_metadata` and builds the same loop with
:func:`build_control_loop`.
"""

from __future__ import annotations

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
#: the JSON types each key may take
_TYPES: dict[str, tuple[type, ...]] = {
    "blending": (int,), "weight_set": (int,), "warmup_ticks": (int, type(None)),
    "single_model": (int, type(None)), "excitation": (bool,)}


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
    def from_metadata(cls, metadata: Mapping[str, str]) -> LoopSettings:
        """The settings a recording was made with, from its metadata (:meth:`metadata`;
        every recording of the current format has them).  Raises ``ValueError`` naming
        the key that is missing or not of its type."""
        meta: dict[str, Any] = {}
        for key in _KEYS:
            try:
                meta[key] = json.loads(metadata[key])
            except KeyError:
                raise ValueError(f"the recording's metadata has no loop setting {key!r}"
                                 ) from None
            except (json.JSONDecodeError, TypeError):
                raise ValueError(f"the recording's loop setting {key!r} is not JSON: "
                                 f"{metadata[key]!r}") from None
        for key, kinds in _TYPES.items():
            v = meta[key]
            if isinstance(v, bool) != (bool in kinds) or not isinstance(v, kinds):
                raise ValueError(f"the recording's loop setting {key!r} = {v!r}: expected "
                                 + " or ".join("null" if k is type(None) else k.__name__
                                               for k in kinds))
        return cls(meta["blending"], meta["weight_set"], meta["warmup_ticks"],
                   meta["single_model"], meta["excitation"])


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
