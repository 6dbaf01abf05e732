"""The Backend contract for a hand of Dynamixel servos holding an object: every finger on
one bus.

Each `read_hand` is one bus cycle for the whole hand: one Fast Sync Read (Sync Read on older
firmware) of every servo of every finger, plus one Sync Write when a step has new goals.
Each finger's encoders go through its own forward kinematics to its fingertip centre in the
hand frame. A step is compliant (current-based position mode, the hand's goal current): a
moving finger's goal is its centre moved by the command plus a short `press` along the way
it pushes on the object, so the object, not the goal, decides where the tip rests; a
manipulation turns the tip-roll servos as well. The step is done once every joint has
settled. A finger that then draws no current presses on nothing: the object has dropped.

Lifecycle, settings, fault latching and recovery are `DynamixelBackend`'s (a finger is a
hand of one); only reading and stepping a hand of several fingers differ.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.backend import (
    FingerState,
    HandCommand,
    HandState,
    PlanarHand,
    check_hand_command,
)
from firmware_if.dxl_bus import ServoReading
from firmware_if.dynamixel_backend import DynamixelBackend, StepSettings, check_cycle_budget
from firmware_if.errors import HandConfigError, HardwareFault, NotReadyError
from firmware_if.hand import Finger, Hand, joint_ticks, load_hand
from firmware_if.registers import RAD_PER_TICK, amp_to_current, rad_to_ticks, ticks_to_rad

HAND_PRESS = 0.0005
"""Metres a moving fingertip's goal lies beyond its target, towards the object: enough to
press (a few encoder ticks), small so that where the object stops it is where it was sent."""
PRESSING = 0.5
"""A finger touches something when a joint draws at least this fraction of the goal current."""


class DynamixelHand(PlanarHand, DynamixelBackend):  # type: ignore[misc]
    """Several planar fingers of Dynamixel servos on one bus, implementing
    `firmware_if.backend.Backend` (see module docstring)."""

    def __init__(self, hand: Hand, port: str, settings: StepSettings | None = None) -> None:
        if len(hand.fingers) < 2:
            raise HandConfigError(f"hand '{hand.name}' has one finger: drive it with "
                                  "DynamixelBackend")
        super().__init__(hand, port, settings or StepSettings(press=HAND_PRESS))
        self.fingers: tuple[Finger, ...] = hand.fingers
        n = len(self.fingers)
        self._qs = [np.asarray(f.home, dtype=np.float64) for f in self.fingers]
        self._goal_q: list[np.ndarray | None] = [None] * n
        self._push = [np.zeros(2)] * n
        self._touching = [False] * n
        self._dropped = False
        self._step: _HandStep | None = None  # type: ignore[assignment]
        self._pressing_raw = max(1, int(PRESSING * amp_to_current(hand.goal_current_a)))

    @classmethod
    def from_cli(cls, *, port: str, hand: str,
                 cycle_budget_s: float = StepSettings.cycle_budget_s) -> DynamixelHand:
        """Build from `haptic run --object` options (no I/O: that happens in `open`)."""
        check_cycle_budget(cycle_budget_s)
        return cls(load_hand(hand), port,
                   StepSettings(press=HAND_PRESS, cycle_budget_s=cycle_budget_s))

    def centre_sigma(self) -> np.ndarray:
        """1-sigma error (metres, per hand axis) of each centre from encoder rounding: (n, 3)."""
        return np.array([RAD_PER_TICK / np.sqrt(12.0)
                         * np.sqrt(np.sum(kin.jacobian(f, q) ** 2, axis=1))
                         for f, q in zip(self.fingers, self._qs, strict=True)])

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        self._dropped = False
        self._step = None
        super().open()

    def set_torque(self, on: bool) -> None:
        """Torque on holds every finger where it is (on the object it was closed on)."""
        self._require_open()
        if not on:
            super().set_torque(False)
            return
        if self._fault:
            raise HardwareFault(f"cannot enable torque while faulted: {self._fault}; reset first")
        self._settings_hold()
        state = self._tolerant_read()
        goals: dict[int, int] = {}
        for i, (finger, f) in enumerate(zip(self.fingers, state.fingers, strict=True)):
            q = np.asarray(f.joints)
            goals.update(joint_ticks(finger.joints, q))
            self._goal_q[i] = q
            inward = np.asarray(self.hand.grasp_centre) - _xz(f.centre)
            self._push[i] = inward / max(float(np.hypot(*inward)), 1e-12)
        self.bus.write_goals(goals)
        self.bus.torque(True)
        self._torque = True

    # -- I/O -------------------------------------------------------------------------------
    def read_hand(self) -> HandState:
        state = self._poll()
        if state is None:
            return self._stale()
        if self._step is not None:
            self._advance_hand(state)
            state = self._stamp(state)
        self._state = state
        return state

    def command_hand(self, command: HandCommand) -> None:
        self._require_open()
        check_hand_command(command, hand=self.hand.name, fingers=len(self.fingers),
                           fault=self._fault, torque_on=self._torque,
                           busy=self._step is not None, dropped=self._dropped)
        state = self._state or self._read()
        goals: dict[int, int] = {}
        goal_q = list(self._goal_q)
        for i in command.moving:
            move = command.moves[i]
            assert move is not None
            finger, f = self.fingers[i], state.fingers[i]
            centre = _xz(f.centre)
            target = centre + (move.dx, move.dz) + self.settings.press * self._push_way(i, f)
            ik = kin.inverse(finger, np.array([target[0], 0.0, target[1]]),
                             np.asarray(f.joints), tolerance=2e-5)
            if not bool(ik.reachable):  # beyond a joint limit: nothing moves
                self._steps_done += 1
                self._blocked = True
                return
            goal_q[i] = ik.q
            goals.update(joint_ticks(finger.joints, ik.q))
            roll = finger.tip_roll  # a tip with no roll servo rolls freely: in a turn it
            # rolls as the object makes it (a held-out hand's turn raised a ValueError here)
            if move.roll and roll is not None and f.tip_roll is not None:
                goals[roll.id] = rad_to_ticks(f.tip_roll + move.roll, roll.zero_ticks,
                                              roll.direction)
        self._blocked = False
        self._goal_q = goal_q
        self._pending_goals = goals  # one Sync Write, with the next read
        self._step = _HandStep(t0=time.monotonic())

    # -- internals -------------------------------------------------------------------------
    def _push_way(self, i: int, f: FingerState) -> np.ndarray:
        """The unit way finger i presses on the object: from its centre towards where its
        goal holds it (the contact's normal, as compliance finds it), else the way it was."""
        goal = self._goal_q[i]
        if goal is not None:
            reach = kin.forward(self.fingers[i], goal)
            gap = np.array([reach[0], reach[2]]) - _xz(f.centre)
            length = float(np.hypot(*gap))
            if length > self.settings.press / 2:
                self._push[i] = gap / length
        return self._push[i]

    def _advance_hand(self, state: HandState) -> None:
        step = self._step
        assert step is not None
        positions = tuple(a for f in state.fingers for a in f.joints)
        step.cycles += 1
        settled = step.last == positions and not self._joints_moving and step.cycles > 2
        step.last = positions
        timed_out = time.monotonic() - step.t0 > self.settings.timeout_s
        if not (settled or timed_out):
            return
        if settled and not all(self._touching):
            try:  # a servo that restarted (a brown-out) presses on nothing too
                self.bus.check_torque(patient=True)
            except HardwareFault as exc:
                self._fault, self._torque = self._fault or str(exc), False
                self._finish(blocked=True)
                return
            self._dropped = True  # a finger pressing on nothing: the object is gone
        self._finish(blocked=not settled)

    def _finish(self, blocked: bool) -> None:
        self._steps_done += 1
        self._blocked = blocked
        self._step = None

    def _touch_down(self) -> None:  # a hand's fingers start closed on the object
        return

    def _state_from(self, readings: dict[int, ServoReading]) -> HandState:  # type: ignore[override]
        fingers = []
        moving = False
        for i, finger in enumerate(self.fingers):
            q = np.array([ticks_to_rad(readings[j.id].position, j.zero_ticks, j.direction)
                          for j in finger.joints])
            self._qs[i] = q
            moving = moving or any(readings[j.id].velocity for j in finger.joints)
            self._touching[i] = any(abs(readings[j.id].current) >= self._pressing_raw
                                    for j in finger.joints)
            centre = kin.forward(finger, q)
            roll = finger.tip_roll
            tip_roll = None if roll is None else ticks_to_rad(readings[roll.id].position,
                                                              roll.zero_ticks, roll.direction)
            fingers.append(FingerState(t_ns=0, centre=(float(centre[0]), float(centre[1]),
                                                       float(centre[2])),
                                       joints=tuple(float(a) for a in q), tip_roll=tip_roll))
        self._joints_moving = moving
        return self._stamp(HandState(t_ns=time.monotonic_ns(), fingers=tuple(fingers)))

    def _stamp(self, state: HandState) -> HandState:  # type: ignore[override]
        stamped = tuple(FingerState(t_ns=state.t_ns, centre=f.centre,
                                    moving=self._step is not None, blocked=self._blocked,
                                    steps_done=self._steps_done, joints=f.joints,
                                    tip_roll=f.tip_roll, torque_on=self._torque,
                                    fault=self._fault)
                        for f in state.fingers)
        return HandState(t_ns=state.t_ns, fingers=stamped, dropped=self._dropped)

    def _stale(self) -> HandState:  # type: ignore[override]
        if self._state is None:
            raise NotReadyError("no valid reading from the bus yet")
        return self._stamp(self._state)  # type: ignore[arg-type]


def _xz(centre: tuple[float, float, float]) -> np.ndarray:
    return np.array([centre[0], centre[2]])


@dataclass
class _HandStep:
    t0: float
    last: tuple[float, ...] | None = None
    cycles: int = 0
    """Bus cycles since the goals were sent."""
