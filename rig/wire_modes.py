"""The one map between the controller's blending modes (``controller.modes.Blending``,
which owns the names and the runtime's codes) and the wire's (the DBC ``VAL_`` table of
ControllerStatus.Blending, ``rig.wire.protocol.Blending``, which owns the numbers on the
CAN bus).  ``tests/test_wire_generated.py`` checks it is complete and one-to-one."""

from __future__ import annotations

from types import MappingProxyType
from typing import Final

from controller.modes import Blending
from rig.wire.protocol import Blending as WireBlending

__all__ = ["TO_WIRE", "from_wire", "to_wire"]

#: controller mode -> the DBC value the ControllerStatus frame carries
TO_WIRE: Final = MappingProxyType({
    Blending.FUZZY: WireBlending.FUZZY,
    Blending.BAYES: WireBlending.BAYES,
    Blending.MOVING: WireBlending.MOVING,
    Blending.LQG: WireBlending.LQG,
})
_FROM_WIRE: Final = MappingProxyType({w: b for b, w in TO_WIRE.items()})
#: :data:`TO_WIRE` as plain ints, for the loop's heartbeat (an enum built per call costs
#: the heartbeat tick microseconds with cold caches)
_TO_WIRE_CODE: Final = MappingProxyType({int(b): int(w) for b, w in TO_WIRE.items()})


def to_wire(blending: Blending | int) -> int:
    """The controller's mode (or its code) -> the wire value (ValueError if unknown)."""
    code = _TO_WIRE_CODE.get(blending)      # a Blending hashes as its int code
    if code is None:
        return int(TO_WIRE[Blending(int(blending))])    # ValueError: no such mode
    return code


def from_wire(value: int) -> Blending:
    """A wire value -> the controller's mode (ValueError if the DBC has no such value)."""
    return _FROM_WIRE[WireBlending(int(value))]
