"""The Backend contract: the one thing the service knows about a hand, real or simulated.

A hand is one or more fingers on one bus; a single finger is a hand of one. A backend
reports every fingertip centre in the hand's own frame (metres) in one read (`read_hand`)
and executes compliant steps given in that frame: one finger moving while the others hold
(exploring), or all of them together (manipulating), `command_hand`. A single finger's
`read_state` and `command_step` are the same for a hand of one, kept as its shorthand.
Stepping is asynchronous so that a real-time loop never waits on motion: a command starts
a step, a later read says when it is done.
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
    """Move one fingertip centre by (dx, dy, dz) metres in the hand frame, staying in
    contact (along the contact's normal the object has the last word), and turn its rolling
    tip by `roll` radians (counter-clockwise seen with x right and z up). A finger on a
    surface moves in x-y; a finger of a planar hand in x-z. Exploring, a tip rolls along the
    object by itself (roll 0); manipulating, turning it rolls the object."""

    dx: float = 0.0
    dy: float = 0.0
    dz: float = 0.0
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
    """A hand the service can read and move (a single finger is a hand of one).
    Implementations: the simulated finger and hand, Dynamixel."""

    def open(self) -> None:
        """Acquire the hardware (or simulation). No I/O happens before this."""

    def close(self) -> None:
        """Torque off and release everything `open` acquired. Safe to call twice."""

    def set_torque(self, on: bool) -> None:
        """Enable or disable the actuators (lifecycle: inactive <-> active)."""

    def read_hand(self) -> HandState:
        """Read every finger now, in one bus read."""

    def finger_names(self) -> tuple[str, ...]:
        """Each finger's name, in the order `read_hand` gives them (a hand file's names; a
        simulated finger's "finger"): a client shows them beside each finger's state."""

    def command_hand(self, command: HandCommand) -> None:
        """Start a step of the fingers that move (the others hold); completion shows as
        `moving=False` in a later state. Refused with a clear error while faulted, with
        torque off, during a step, or for a move the hand cannot make (a finger on a
        surface cannot turn its tip into the object: `roll` is for planar hands)."""

    def read_state(self) -> FingerState:
        """A single finger's shorthand: its state (the first finger's, for a hand)."""

    def command_step(self, step: StepCommand) -> None:
        """A single finger's shorthand: `command_hand` with one move (dx, dy)."""

    def clear_fault(self) -> list[str]:
        """Reset a latched fault (torque stays off). Returns what the reset found and did
        that the operator should know, in words (a servo with a hardware error rebooted)."""


def check_can_step(*, fault: str | None, torque_on: bool, busy: bool,
                   what: str = "finger") -> None:
    """The contract's preconditions for `command_step`, raised the same way by every backend
    (`what` names the finger or the hand in the words)."""
    if fault:  # a bus's fault already says how to recover: not twice
        raise HardwareFault(f"{what} is faulted: {fault}"
                            + ("" if "to recover" in fault else "; reset first"))
    if not torque_on:
        raise NotReadyError(f"torque is off: activate the {what} before stepping")
    if busy:
        raise NotReadyError("a step is still under way")


def check_hand_command(command: HandCommand, *, hand: str, fingers: int, fault: str | None,
                       torque_on: bool, busy: bool, dropped: bool) -> None:
    """The contract's preconditions for `command_hand` of a planar hand, raised the same way
    by every implementation: as `check_can_step`, then a held object, a move (or None) per
    finger, at least one moving, all in the hand's x-z plane."""
    check_can_step(fault=fault, torque_on=torque_on, busy=busy,
                   what="hand" if fingers > 1 else "finger")
    if dropped:
        raise NotReadyError("the object was dropped: nothing left to explore")
    if len(command.moves) != fingers:
        raise ValueError(f"a command for hand '{hand}' needs {fingers} moves (None for a "
                         f"finger that holds), got {len(command.moves)}")
    if not command.moving:
        raise ValueError("a command moves at least one finger")
    if any(m is not None and m.dy for m in command.moves):
        raise ValueError(f"hand '{hand}' moves in its x-z plane: dy must be 0")


class PlanarHand:
    """A single finger's shorthand on a planar hand: `read_state` is the first finger's
    state, and steps go through `command_hand` (a finger of a hand moves in x-z)."""

    def read_state(self) -> FingerState:
        return self.read_hand().fingers[0]  # type: ignore[attr-defined]

    def command_step(self, step: StepCommand) -> None:
        raise ValueError(f"hand '{self.hand.name}' moves in its x-z plane: step it with "  # type: ignore[attr-defined]
                         "command_hand (a FingerMove per finger)")

    def finger_names(self) -> tuple[str, ...]:
        return self.hand.finger_names  # type: ignore[attr-defined]


class HandOfOne:
    """`read_hand` and `command_hand` for a backend of one finger, in terms of its
    `read_state` and `command_step`: a single finger is a hand of one."""

    def read_hand(self) -> HandState:
        state = self.read_state()  # type: ignore[attr-defined]
        return HandState(t_ns=state.t_ns, fingers=(state,))

    def finger_names(self) -> tuple[str, ...]:
        return ("finger",)

    def command_hand(self, command: HandCommand) -> None:
        if len(command.moves) != 1:
            raise ValueError(f"a hand of one finger takes one move, got {len(command.moves)}")
        move = command.moves[0]
        if move is None:
            raise ValueError("a command moves at least one finger")
        if move.roll or move.dz:
            raise ValueError("a finger on a surface steps in x-y: its height is the "
                             "surface's, and its tip rolls by itself (dz and roll must be 0)")
        self.command_step(StepCommand(move.dx, move.dy))  # type: ignore[attr-defined]
