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


@dataclass(frozen=True)
class FingerMove:
    """Move one fingertip centre by (dx, dz) metres in the hand plane and turn its rolling
    tip by `roll` radians (counter-clockwise seen with x right and z up). Exploring, a tip
    rolls along the object by itself (roll 0); manipulating, turning it rolls the object."""

    dx: float
    dz: float
    roll: float = 0.0


@dataclass(frozen=True)
class HandCommand:
    """One step of a hand: a move per finger, None for a finger that holds. One finger
    moving explores; all moving together manipulate the object."""

    moves: tuple[FingerMove | None, ...]

    @property
    def moving(self) -> tuple[int, ...]:
        return tuple(i for i, m in enumerate(self.moves) if m is not None)


@dataclass(frozen=True)
class HandState:
    """One consistent reading of every finger of a hand (one bus read)."""

    t_ns: int
    fingers: tuple[FingerState, ...]
    """Per finger; each `centre` is (x, y, z) in the hand frame, y = 0 for a planar hand."""
    dropped: bool = False
    """The held object slipped out of the grasp: the episode is over."""

    @property
    def moving(self) -> bool:
        return any(f.moving for f in self.fingers)


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
