"""Fail-safe lifecycle of the controller service.

::

                 arm (sensors healthy)
      INACTIVE ------------------------> ACTIVE
         ^  ^  <------------------------   |
         |  |          disarm              | fault
         |  |                              v
         |  +------ reset (condition gone) FAULT (latched)
         |                                 ^
         +------------- fault -------------+
      any state --- shutdown ---> STOPPING (final)

- INACTIVE: sensors monitored, estimator running warm, valve in its safe state
  (Enable=0, spool 0: the rig opens the bypass, passive suspension).
- ACTIVE: the bank's force reference drives the valve through the PI force loop.
- FAULT: latched with reason (FaultCode), tick and detail; valve safe.  Left only by an
  explicit reset, which is refused while the fault condition is still present.
- STOPPING: shutdown; valve safe; final.

Only ACTIVE enables the valve (:attr:`Lifecycle.valve_enabled`).  Every transition is
logged (``logging``, i.e. the journal under systemd) and handed to the listeners (the
service publishes and records it).  Transitions are rare, so they may allocate.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from rig.wire.protocol import FaultCode, LifecycleState

__all__ = ["CommandResult", "Lifecycle", "Transition"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Transition:
    """One lifecycle change (published and recorded)."""

    tick: int
    t_ns: int
    previous: LifecycleState
    state: LifecycleState
    reason: str
    fault_code: FaultCode = FaultCode.NONE
    fault_detail: int = 0
    #: into FAULT: the lateness measured around the fault
    #: (:meth:`rig.service.host_lateness.HostLateness.as_dict`), else None
    host_lateness: dict[str, object] | None = None

    def as_dict(self) -> dict[str, object]:
        d: dict[str, object] = {
            "tick": self.tick, "t_ns": self.t_ns, "from": self.previous.name,
            "to": self.state.name, "reason": self.reason,
            "fault": self.fault_code.name, "detail": self.fault_detail}
        if self.host_lateness is not None:
            d["host_lateness"] = self.host_lateness
        return d


@dataclass(frozen=True)
class CommandResult:
    """Outcome of an operator command (arm / disarm / reset)."""

    accepted: bool
    state: LifecycleState
    message: str

    def as_dict(self) -> dict[str, object]:
        return {"accepted": self.accepted, "state": self.state.name, "message": self.message}


Listener = Callable[[Transition], None]


class Lifecycle:
    """The state machine; pure logic (the loop supplies the health facts)."""

    def __init__(self) -> None:
        self.state = LifecycleState.INACTIVE
        #: True only in ACTIVE: every other state commands the safe valve state (kept
        #: with ``state`` by the one method that changes it; read every tick)
        self.valve_enabled = False
        self.fault_code = FaultCode.NONE
        self.fault_tick = -1
        self.fault_detail = 0
        self.fault_message = ""
        #: the latched fault's host-lateness record (None: none latched / not assessed)
        self.fault_host_lateness: dict[str, object] | None = None
        self.transitions = 0
        self._listeners: list[Listener] = []

    # ------------------------------------------------------------------ queries
    @property
    def latched(self) -> bool:
        return self.state is LifecycleState.FAULT

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    # ------------------------------------------------------------------ transitions
    def _go(self, state: LifecycleState, tick: int, t_ns: int, reason: str,
            code: FaultCode = FaultCode.NONE, detail: int = 0,
            host_lateness: dict[str, object] | None = None) -> None:
        tr = Transition(tick, t_ns, self.state, state, reason, code, detail, host_lateness)
        self.state = state
        self.valve_enabled = state is LifecycleState.ACTIVE
        self.transitions += 1
        level = logging.ERROR if state is LifecycleState.FAULT else logging.INFO
        log.log(level, "lifecycle %s -> %s at tick %d: %s", tr.previous.name, state.name,
                tick, reason)
        for listener in self._listeners:
            try:
                listener(tr)
            except Exception:  # a listener must never break the safety path
                log.exception("lifecycle listener failed")

    def arm(self, tick: int, t_ns: int, healthy: bool, why_not: str = "") -> CommandResult:
        """INACTIVE -> ACTIVE, only when the loop reports healthy sensors/estimator."""
        if self.state is LifecycleState.ACTIVE:
            return CommandResult(True, self.state, "already ACTIVE")
        if self.state is not LifecycleState.INACTIVE:
            return CommandResult(False, self.state, f"cannot arm from {self.state.name}")
        if not healthy:
            return CommandResult(False, self.state, f"arm refused: {why_not or 'not healthy'}")
        self._go(LifecycleState.ACTIVE, tick, t_ns, "armed")
        return CommandResult(True, self.state, "armed")

    def disarm(self, tick: int, t_ns: int, reason: str = "disarmed") -> CommandResult:
        """ACTIVE -> INACTIVE (no-op in INACTIVE; FAULT stays latched)."""
        if self.state is LifecycleState.ACTIVE:
            self._go(LifecycleState.INACTIVE, tick, t_ns, reason)
            return CommandResult(True, self.state, reason)
        if self.state is LifecycleState.INACTIVE:
            return CommandResult(True, self.state, "already INACTIVE")
        return CommandResult(False, self.state, f"cannot disarm from {self.state.name}")

    def fault(self, code: FaultCode, tick: int, t_ns: int, detail: int = 0,
              message: str = "", host_lateness: dict[str, object] | None = None) -> bool:
        """Latch ``code`` (from INACTIVE or ACTIVE).  True if this call latched it.
        ``host_lateness``: the lateness measured around it (kept and recorded)."""
        if self.state in (LifecycleState.FAULT, LifecycleState.STOPPING):
            return False
        self.fault_code = code
        self.fault_tick = tick
        self.fault_detail = detail & 0xFF
        self.fault_message = message or code.name
        self.fault_host_lateness = host_lateness
        self._go(LifecycleState.FAULT, tick, t_ns, f"fault {code.name}: {self.fault_message}",
                 code, self.fault_detail, host_lateness)
        return True

    def reset(self, tick: int, t_ns: int, condition: FaultCode,
              why: str = "") -> CommandResult:
        """FAULT -> INACTIVE, refused while a fault ``condition`` is present now
        (``why``: optional explanation added to the refusal)."""
        if self.state is not LifecycleState.FAULT:
            return CommandResult(self.state is LifecycleState.INACTIVE, self.state,
                                 f"nothing to reset in {self.state.name}")
        if condition is not FaultCode.NONE:
            return CommandResult(False, self.state,
                                 f"reset refused: {condition.name} still present"
                                 + (f" ({why})" if why else ""))
        cleared = self.fault_code
        self._go(LifecycleState.INACTIVE, tick, t_ns, f"reset (cleared {cleared.name})")
        self.fault_code = FaultCode.NONE
        self.fault_tick = -1
        self.fault_detail = 0
        self.fault_message = ""
        self.fault_host_lateness = None
        return CommandResult(True, self.state, f"reset, cleared {cleared.name}")

    def stop(self, tick: int, t_ns: int, reason: str = "shutdown") -> None:
        """Any state -> STOPPING (final)."""
        if self.state is not LifecycleState.STOPPING:
            self._go(LifecycleState.STOPPING, tick, t_ns, reason)
