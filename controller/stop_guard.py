"""End-stop guard of the bank's force reference (docs/design.md §9.6).

The LQ gains know nothing about the bump stops: set 1 cancels most of the suspension
spring between ~0.1 and 0.5 Hz, so on a plant whose spring is much softer than the
design's the force can push the suspension quasi-statically into a stop.  The guard
lets no force push toward a stop once the LVDT reading, led by the approach rate, is
within ``width_m`` of it:

    s = clip((r_hi - r - t_lead max(r' - v0, 0)) / width, 0, 1)   toward compression (F < 0)
    s = clip((r - r_lo - t_lead max(-r' - v0, 0)) / width, 0, 1)  toward rebound     (F > 0)
    F_out = s F

r the LVDT reading (compression positive), r' its rate (the force loop's filtered LVDT
rate, compression positive), r_lo / r_hi the readings where the rebound / compression
stops engage (``Design.bump_stop``), F > 0 extends the suspension.  The lead
t_lead = ``lead_s`` over the part of the approach rate above the deadband v0 =
``deadband_mps`` fades the force earlier in a fast approach: the force loop needs about
20 ms to unload, which a suspension closing at 1-3 m/s covers in 20-60 mm (docs/design.md
§9.6); below the deadband (the wheel hop's rate) the guard is the plain distance law.  A
force away from the stop is never changed, the output is continuous in r, r' and F, and
at the stop the force toward it is 0: the suspension there is the passive one (the
actuator with the flow feedforward is transparent at zero force reference).

This is the plain-Python statement of the law, used by tests/support/reference_bank.py and
hil/sim/fullstate.py; the runtime's numba kernel is ``controller.runtime.kernels.stop_guard``.
"""

from __future__ import annotations

import math

__all__ = ["stop_guard_scale"]


def stop_guard_scale(force_n: float, rattlespace_m: float, rebound_stop_m: float,
                     compression_stop_m: float, width_m: float, rate_mps: float = 0.0,
                     lead_s: float = 0.0, deadband_mps: float = 0.0) -> float:
    """The factor s in [0, 1] the guard applies to ``force_n`` [N] at the LVDT reading
    ``rattlespace_m`` [m] and its rate ``rate_mps`` [m/s, compression positive; a
    non-finite rate counts as 0], with lead ``lead_s`` [s] above ``deadband_mps`` [m/s]
    (1 when ``width_m`` <= 0: guard off)."""
    if width_m <= 0.0:
        return 1.0
    if not math.isfinite(rate_mps):
        rate_mps = 0.0
    if force_n < 0.0:
        s = (compression_stop_m - rattlespace_m
             - lead_s * max(rate_mps - deadband_mps, 0.0)) / width_m
    elif force_n > 0.0:
        s = (rattlespace_m - rebound_stop_m
             - lead_s * max(-rate_mps - deadband_mps, 0.0)) / width_m
    else:
        return 1.0
    return min(max(s, 0.0), 1.0)
