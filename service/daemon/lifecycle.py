"""The daemon's lifecycle as an explicit transition table.

unconfigured --configure--> inactive --activate--> active --deactivate--> inactive
any opened state --fault--> fault (latched, torque off) --reset or configure--> inactive

Inactive means the backend is open, torque is off and state is streamed. Nothing is
commanded to the servos (not even torque) until a first valid read since the backend was
opened: `Lifecycle.require_valid_read` is the gate every command path goes through.
"""

from __future__ import annotations

from enum import StrEnum

from service.errors import StateError


class State(StrEnum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FAULT = "fault"


TRANSITIONS: dict[str, dict[State, State]] = {
    "configure": {State.UNCONFIGURED: State.INACTIVE, State.INACTIVE: State.INACTIVE,
                  State.FAULT: State.INACTIVE},  # a new backend (e.g. on a new port)
    "activate": {State.INACTIVE: State.ACTIVE},
    "deactivate": {State.ACTIVE: State.INACTIVE, State.INACTIVE: State.INACTIVE},
    "fault": {State.INACTIVE: State.FAULT, State.ACTIVE: State.FAULT, State.FAULT: State.FAULT},
    "reset": {State.FAULT: State.INACTIVE},
    "shutdown": {s: State.UNCONFIGURED for s in State},
}
"""event -> {from state: to state}; anything missing is refused."""

WAY_OUT: dict[State, tuple[State, str]] = {
    State.UNCONFIGURED: (State.INACTIVE, "configure the daemon first"),
    State.INACTIVE: (State.ACTIVE, "activate first"),
    State.ACTIVE: (State.INACTIVE, "deactivate first"),
    State.FAULT: (State.INACTIVE, "reset clears the fault once its cause is mended"),
}
"""What leaves each state, and the state it leads to, for a refusal's words: a client
refused "while fault" was not told that `reset` is the way out (a held-out lab). Said only
where it leads to a state that allows the request: "cannot reset while inactive ...
(activate first)" sent a held-out client the wrong way."""


class Lifecycle:
    """Current state, the last fault and whether the backend has been read since opening."""

    def __init__(self) -> None:
        self.state = State.UNCONFIGURED
        self.fault: str | None = None
        self.valid_read = False

    def allowed(self, event: str) -> bool:
        return self.state in TRANSITIONS.get(event, {})

    def check(self, event: str, command: str | None = None) -> State:
        """The state `event` leads to, or StateError saying which states allow it (naming
        `command`, the request that asked for it, if not the event itself)."""
        table = TRANSITIONS.get(event)
        if table is None:
            raise StateError(f"unknown lifecycle event '{event}'")
        if self.state not in table:
            allowed = ", ".join(s.value for s in table)
            leads_to, way_out = WAY_OUT[self.state]
            hint = (f" ({way_out})" if leads_to in table
                    else _nothing_to_reset(self.state) if event == "reset" else "")
            raise StateError(f"cannot {command or event} while {self.state.value}; allowed in: "
                             f"{allowed}{hint}")
        return table[self.state]

    def apply(self, event: str, reason: str | None = None) -> tuple[State, State]:
        """Make the transition; returns (old, new)."""
        new = self.check(event)
        old = self.state
        self.state = new
        if event == "fault":
            self.fault = _with_cause(self.fault if old is State.FAULT else None, reason)
        elif event in ("reset", "shutdown", "configure"):
            self.fault = None
        if event in ("configure", "reset", "shutdown"):
            self.valid_read = False
        return old, new

    def mark_read(self) -> None:
        self.valid_read = True

    def require_valid_read(self) -> None:
        if not self.valid_read:
            raise StateError("no valid reading from the finger yet; wait for state to stream")


CAUSES = 4
"""Most causes a latched fault's text names: the first, then the latest."""


def _with_cause(fault: str | None, reason: str | None) -> str:
    """A fault's text with `reason` added: the first cause is kept (an estop in fault does
    not erase a servo's diagnosis), a cause already named is not named again, and past
    `CAUSES` the middle ones give way to the latest."""
    if not fault:
        return reason or "fault"
    causes = fault.split("; then ")
    if reason and reason not in causes:
        causes.append(reason)
    if len(causes) > CAUSES:
        causes = [causes[0], "...", *causes[-(CAUSES - 2):]]
    return "; then ".join(causes)


def _nothing_to_reset(state: State) -> str:
    """A refused reset's way out: none needed, or, unconfigured (a start-up whose port was
    not there), a `configure` (a held-out lab's emulator came back, and `reset` said only
    that no fault was latched)."""
    if state is State.UNCONFIGURED:
        return (" (no fault is latched: send configure, {} to try the daemon's own "
                "configuration again)")
    return " (no fault is latched: nothing to reset)"
