"""How the service and the emulated rig keep time in ``rig demo`` (``--timing``).

* ``realtime`` -- each process on its own absolute 1 kHz deadlines
  (:class:`rig.rt.pacing.Pacer`), as ``rig run`` and ``rig hil`` on the bench: a host that
  stalls a real-time thread for a few milliseconds shows as SENSOR_STALE / the rig's drive
  watchdog, which is what those checks are for;
* ``lockstep`` -- in turns, tick by tick (:mod:`rig.rt.lockstep`): the host's stalls only
  slow the run down;
* ``auto`` -- resolved by :func:`choose_timing`, the one place that decides.
"""

from __future__ import annotations

__all__ = ["TIMINGS", "choose_timing"]

#: the timings a run can have ("auto" is resolved to one of them)
TIMINGS = ("realtime", "lockstep")


def choose_timing(requested: str) -> tuple[str, str]:
    """The timing a run that asked for ``requested`` (one of :data:`TIMINGS` or "auto")
    gets, and why (one line).  The single seam for "auto": it picks lockstep until a
    check of the host's real-time ability (``rig check-host``) exists; wire that check
    in here, and only here, to pick realtime on a host that keeps 1 kHz deadlines."""
    if requested in TIMINGS:
        return requested, "asked for"
    if requested != "auto":
        raise ValueError(f"timing {requested!r}: expected auto or one of {', '.join(TIMINGS)}")
    return "lockstep", ("auto: this host's real-time ability is not checked yet; lockstep "
                        "does not depend on it")
