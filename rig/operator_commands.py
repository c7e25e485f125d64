"""The operator commands of the service: one table owns each command's name, its JSON
argument schema (what Zenoh telemetry accepts), the converter to the argument the loop
applies, and whether it is refused while the controller is ACTIVE.

The control loop (:class:`rig.service.loop.ControlLoop`) holds one handler per entry of
:data:`OPERATOR_COMMANDS` and checks at construction that it has exactly these.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Final

from controller.modes import blending_of

__all__ = ["OPERATOR_COMMANDS", "OperatorCommand", "brief", "loop_argument",
           "validate_command"]

_NAME_CHARS = 40      # an unknown command or argument name is shown cut to this length


def brief(value: object, limit: int = _NAME_CHARS) -> str:
    """repr(value), cut to ``limit`` characters (error texts never echo large input)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 3]}..."


@dataclass(frozen=True)
class OperatorCommand:
    """One operator command."""

    name: str
    #: argument -> the JSON types accepted for it; no other arguments are accepted
    arguments: Mapping[str, tuple[type, ...]]
    #: validated JSON arguments -> the argument :meth:`ControlLoop.request` takes
    to_loop: Callable[[Mapping[str, Any]], Any]
    #: refused while ACTIVE ("disarm first"): it changes what the bank computes
    needs_inactive: bool
    help: str


def _nothing(_args: Mapping[str, Any]) -> None:
    return None


OPERATOR_COMMANDS: Final[Mapping[str, OperatorCommand]] = {c.name: c for c in (
    OperatorCommand("arm", {}, _nothing, False,
                    "INACTIVE -> ACTIVE when the sensors, estimator and rig are healthy"),
    OperatorCommand("disarm", {}, _nothing, False, "ACTIVE -> INACTIVE (passive)"),
    OperatorCommand("reset", {}, _nothing, False,
                    "FAULT -> INACTIVE once the fault's cause has cleared"),
    OperatorCommand("blending", {"blending": (str, int)},
                    lambda a: int(blending_of(a["blending"])), True,
                    "controller mode (controller/modes.py names or numbers)"),
    OperatorCommand("weight_set", {"weight_set": (int,)},
                    lambda a: int(a["weight_set"]), True, "LQ weight set of the design"),
    OperatorCommand("road", {"speed_mps": (int, float), "roughness_gd": (int, float)},
                    lambda a: (float(a["speed_mps"]), float(a["roughness_gd"])), True,
                    "road the bank's noise entry is chosen for: speed [m/s], Gd [m^3]"),
)}


def validate_command(name: str, args: object) -> dict[str, Any]:
    """Check a command name and its argument object; ValueError names what is wrong."""
    if name not in OPERATOR_COMMANDS:
        raise ValueError(f"unknown command {brief(name)}: allowed "
                         f"{', '.join(OPERATOR_COMMANDS)}")
    if not isinstance(args, dict):
        raise ValueError(f"command {name!r}: arguments must be a JSON object, "
                         f"got {brief(args)}")
    spec = OPERATOR_COMMANDS[name].arguments
    extra = set(args) - set(spec)
    if extra:
        shown = ", ".join(brief(k) for k in sorted(extra)[:3])
        more = f" and {len(extra) - 3} more" if len(extra) > 3 else ""
        raise ValueError(f"command {name!r}: unknown argument(s) {shown}{more}; "
                         f"allowed {sorted(spec) or 'none'}")
    for key, types in spec.items():
        if key not in args:
            raise ValueError(f"command {name!r}: missing argument {key!r}")
        v = args[key]
        if isinstance(v, bool) or not isinstance(v, types):
            raise ValueError(f"command {name!r}: {key}={brief(v)} must be "
                             f"{' or '.join(t.__name__ for t in types)}")
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"command {name!r}: {key}={v!r} must be finite")
    return args


def loop_argument(name: str, args: Mapping[str, Any]) -> Any:
    """The loop's argument for validated JSON ``args`` of command ``name``."""
    return OPERATOR_COMMANDS[name].to_loop(args)
