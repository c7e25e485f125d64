"""End-stop guard of the bank's force reference (docs/design.md §9.6).

The LQ gains know nothing about the bump stops: set 1 cancels most of the suspension
spring between ~0.1 and 0.5 Hz, so on a plant whose spring is much softer than the
design's the force can push the suspension quasi-statically into a stop.  The guard
lets no force push toward a stop once the LVDT reading is within ``width_m`` of it:

    s = clip((r_hi - r) / width, 0, 1)   for a force toward the compression stop (F < 0)
    s = clip((r - r_lo) / width, 0, 1)   for a force toward the rebound stop     (F > 0)
    F_out = s F

r the LVDT reading (compression positive), r_lo / r_hi the readings where the rebound /
compression stops engage (``Design.bump_stop``), F > 0 extends the suspension.  A force
away from the stop is never changed, the output is continuous in r and F, and at the
stop the force toward it is 0: the suspension there is the passive one (the actuator
with the flow feedforward is transparent at zero force reference).

This is the plain-Python statement of the law, used by tests/support/reference_bank.py and
hil/sim/fullstate.py; the runtime's numba kernel is ``controller.runtime.kernels.stop_guard``.
"""

from __future__ import annotations

__all__ = ["stop_guard_scale"]


def stop_guard_scale(force_n: float, rattlespace_m: float, rebound_stop_m: float,
                     compression_stop_m: float, width_m: float) -> float:
    """The factor s in [0, 1] the guard applies to ``force_n`` [N] at the LVDT reading
    ``rattlespace_m`` [m] (1 when ``width_m`` <= 0: guard off)."""
    if width_m <= 0.0:
        return 1.0
    if force_n < 0.0:
        s = (compression_stop_m - rattlespace_m) / width_m
    elif force_n > 0.0:
        s = (rattlespace_m - rebound_stop_m) / width_m
    else:
        return 1.0
    return min(max(s, 0.0), 1.0)
