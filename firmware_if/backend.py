"""The Backend contract: the one thing the service knows about a finger, real or simulated.

A backend reports the fingertip centre in the hand's own frame (metres) and executes
compliant steps given in that frame. Stepping is asynchronous so that a real-time loop
never waits on motion: `command_step` starts a step, `read_state` says when it is done.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from firmware_if.errors import HardwareFault, NotReadyError


@dataclass(frozen=True)
class FingerState:
    """One consistent reading of the finger."""

    t_ns: int
    """Backend's monotonic clock, nanoseconds."""
    centre: tuple[float, float, float]
    """Fingertip centre in the hand frame, metres."""
    moving: bool = False
    """A commanded step is still under way."""
    blocked: bool = False
    """The last step could not be made (map edge, joint limit, unreachable target)."""
    steps_done: int = 0
    """Number of steps finished since open (blocked ones included); lets callers match replies."""
    joints: tuple[float, ...] = ()
    """Joint angles in radians, where the finger has joints."""
    tip_roll: float | None = None
    """Angle of a continuously rolling tip joint, reported but not used for the centre."""
    torque_on: bool = False
    fault: str | None = None
    """A latched fault, or None when healthy."""


@dataclass(frozen=True)
class StepCommand:
    """Move the fingertip centre by (dx, dy) metres in the hand frame, staying in contact."""

    dx: float
    dy: float


@runtime_checkable
class Backend(Protocol):
    """A finger the service can read and move. Implementations: simulated, Dynamixel."""

    def open(self) -> None:
        """Acquire the hardware (or simulation). No I/O happens before this."""

    def close(self) -> None:
        """Torque off and release everything `open` acquired. Safe to call twice."""

    def set_torque(self, on: bool) -> None:
        """Enable or disable the actuators (lifecycle: inactive <-> active)."""

    def read_state(self) -> FingerState:
        """Read the finger now."""

    def command_step(self, step: StepCommand) -> None:
        """Start a compliant step; completion shows as `moving=False` in a later state."""

    def clear_fault(self) -> None:
        """Reset a latched fault (torque stays off)."""


def check_can_step(*, fault: str | None, torque_on: bool, busy: bool) -> None:
    """The contract's preconditions for `command_step`, raised the same way by every backend."""
    if fault:
        raise HardwareFault(f"finger is faulted: {fault}; reset first")
    if not torque_on:
        raise NotReadyError("torque is off: activate the finger before stepping")
    if busy:
        raise NotReadyError("a step is still under way")
