"""Controller modes: the one table of the names users type (CLI ``--controller``, the
``blending`` operator command, JSON output, the study).

=============  ==========================================================  ===========
name           what runs                                                    bank mode
=============  ==========================================================  ===========
passive        bypass open, valve off (the passive suspension)              --
zero-force     valve closed, force reference 0 (the actuator's own feel)    --
skyhook        skyhook damper on the measured rates (reference law)         --
lqg            one LQG (Kalman filter + LQ gain) on the nominal tire model  LQG
fuzzy          the bank blended by fuzzy logic (thesis ch. 3)               FUZZY
bayes          the bank blended by Bayesian MMAE probabilities              BAYES
moving         the moving bank (models switched along the tire curve)       MOVING
=============  ==========================================================  ===========

The rig service runs the bank modes (:data:`BANK_MODES`, coded as :class:`Blending`);
the offline simulator runs all of :data:`CONTROLLER_MODES`.  This module owns the mode
names and the runtime's codes (recordings and operator commands use them); the CAN wire
has its own numbers (the DBC ``VAL_`` table, ``rig.wire.protocol.Blending``) and
``rig.wire_modes`` maps one onto the other.
"""

from __future__ import annotations

from enum import IntEnum
from types import MappingProxyType
from typing import Final

__all__ = ["BANK_MODES", "CONTROLLER_MODES", "REFERENCE_MODES", "Blending", "blending_of",
           "mode_of"]


class Blending(IntEnum):
    """The bank's blending modes as the runtime step codes them (the ``blending`` of
    recordings, status and the operator command's integer form).  Not the wire's
    numbers: ``rig.wire_modes`` maps these to the DBC's."""

    FUZZY = 0
    BAYES = 1
    MOVING = 2
    LQG = 3

#: modes that need no estimator bank, in the order tables show them
REFERENCE_MODES: Final = ("passive", "zero-force", "skyhook")
#: bank modes -> the blending the runtime step uses
BANK_MODES: Final = MappingProxyType({
    "lqg": Blending.LQG,
    "fuzzy": Blending.FUZZY,
    "bayes": Blending.BAYES,
    "moving": Blending.MOVING,
})
#: every mode the offline simulator runs
CONTROLLER_MODES: Final = (*REFERENCE_MODES, *BANK_MODES)


def blending_of(mode: str | int) -> Blending:
    """Bank mode name (``"fuzzy"``) or mode code (0..3) -> :class:`Blending`.
    ValueError names the allowed values."""
    if isinstance(mode, int) and not isinstance(mode, bool):
        if mode in Blending._value2member_map_:
            return Blending(mode)
    elif isinstance(mode, str) and mode.lower() in BANK_MODES:
        return BANK_MODES[mode.lower()]
    raise ValueError(f"controller {mode!r}: allowed {', '.join(BANK_MODES)} "
                     f"(or 0..{max(Blending)})")


def mode_of(blending: Blending | int) -> str:
    """:class:`Blending` (or its code) -> the mode name users type."""
    b = Blending(int(blending))
    return next(name for name, value in BANK_MODES.items() if value is b)
