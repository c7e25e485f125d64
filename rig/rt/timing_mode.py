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

import threading
from collections.abc import Callable

from rig.rt.hostcheck import HostCheck

__all__ = ["AUTO_CHECK_S", "TIMINGS", "checked_in_own_thread", "choose_timing"]

#: the timings a run can have ("auto" is resolved to one of them)
TIMINGS = ("realtime", "lockstep")

#: length of the host check that "auto" runs [s]
AUTO_CHECK_S = 2.0


def checked_in_own_thread(check: Callable[[], HostCheck]) -> HostCheck:
    """Run ``check`` in a thread of its own, so the real-time set-up it applies (scheduling
    policy, CPU affinity) stays with that thread and not with the caller."""
    out: list[HostCheck] = []
    errors: list[BaseException] = []

    def body() -> None:
        try:
            out.append(check())
        except BaseException as exc:  # re-raised in the caller
            errors.append(exc)

    t = threading.Thread(target=body, name="host-check", daemon=True)
    t.start()
    t.join()
    if errors:
        raise errors[0]
    return out[0]


def choose_timing(requested: str, check: Callable[[], HostCheck] | None = None
                  ) -> tuple[str, str]:
    """The timing a run that asked for ``requested`` (one of :data:`TIMINGS` or "auto")
    gets, and why (one line).  "auto" runs ``check`` (a short ``rig check-host``) and
    picks realtime only where the check holds the configured budgets on a PREEMPT_RT
    kernel: on another kernel a short check that passes proves little (stalls of several
    ms every ~10 s were seen on a host whose 2 s checks often passed), so it is lockstep,
    which does not depend on the host."""
    if requested in TIMINGS:
        return requested, "asked for"
    if requested != "auto":
        raise ValueError(f"timing {requested!r}: expected auto or one of {', '.join(TIMINGS)}")
    if check is None:
        return "lockstep", "auto: the host was not checked; lockstep does not depend on it"
    hc = check()
    lat = hc.latency
    figures = (f"{hc.seconds:g} s host check: max lateness {lat.max_s * 1e6:.0f} us, budget "
               f"{hc.budget.stale_s * 1e6:.0f} us")
    if not hc.ok:
        return "lockstep", f"auto: {figures}, fails; rig check-host says what to change"
    if "PREEMPT_RT" not in hc.kernel:
        return "lockstep", (f"auto: {figures}, passes, but the kernel is not PREEMPT_RT "
                            f"(its stalls come seconds apart)")
    return "realtime", f"auto: {figures}, passes on a PREEMPT_RT kernel"
