"""Hardware in the loop for a hand: the emulated servos of every finger drive the simulated
hand and the object it holds (`sim_backend.hand.SimulatedHand`).

The servos power up where the simulated hand closed its fingers on the object. When the
drives of a finger go somewhere new (a Sync Write of goals), the plant hands the simulated
hand that finger's move: from its fingertip centre to where the drives would put it. One
finger moving without turning its tip explores (its tip presses back onto the contour, the
others hold); a tip-roll goal or several fingers at once manipulate. The simulated hand
applies its own physics: the object's hidden pose, B2's noise when asked, the quasi-static
grasp and its drop. The plant then reports what the simulated hand reads as encoder values
(its measurement noise becomes the encoders' noise) and, while a finger presses on the
object, its current bound as Present Current. After a drop nothing stops the fingers: they
go where their drives are and draw no current.

Each new drive position is one move, so the comparison with the simulated hand holds with
the servos' profile velocity 0 (as the hand presets set it); with a profile a move arrives in
parts, each its own simulated step.
"""

from __future__ import annotations

import threading

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.backend import FingerMove, HandCommand
from firmware_if.errors import FirmwareError
from firmware_if.hand import Hand, joint_ticks
from firmware_if.registers import rad_to_ticks, ticks_to_rad
from service.errors import ServiceError
from sim_backend.emulator.servo import EmulatedServo
from sim_backend.hand import SimulatedHand


class HandPlant:
    """Couples the emulated servos of a hand to a simulated hand (see module docstring).
    `sim` is opened here with its torque on; the plant owns it from then on."""

    def __init__(self, sim: SimulatedHand) -> None:
        self.sim = sim
        self.hand: Hand = sim.hand
        sim.open()
        sim.set_torque(True)
        self.refused = 0
        """Moves the simulated hand refused (a bad command; the fingers stay)."""
        self.moves = 0
        self._seen: dict[int, int] = {}
        self._worker: threading.Thread | None = None
        self._version = -1
        self._reported: list[np.ndarray] = []
        self._rolls = np.zeros(len(self.hand.fingers))
        self._report()
        self._seen = self.home_ticks()

    def home_ticks(self) -> dict[int, int]:
        """Register values where the fingers closed on the object (where the servos power up)."""
        ticks: dict[int, int] = {}
        for finger, q, roll in zip(self.hand.fingers, self._reported, self._rolls, strict=True):
            ticks.update(joint_ticks(finger.joints, q))
            if finger.tip_roll is not None:
                r = finger.tip_roll
                ticks[r.id] = rad_to_ticks(float(roll), r.zero_ticks, r.direction)
        return ticks

    def update(self, servos: dict[int, EmulatedServo]) -> None:
        if any(sid not in servos for sid in self.hand.ids):
            return
        busy = self._worker is not None and self._worker.is_alive()
        if not busy:
            self._worker = None
            drives = {sid: int(round(servos[sid].drive)) for sid in self.hand.ids}
            powered = all(servos[j.id].torque_on for f in self.hand.fingers for j in f.joints)
            if powered and not self.sim.dropped and drives != self._seen:
                busy = self._move(drives)
            self._seen = drives  # without torque (a reboot) the drives follow the joints
        for finger in self.hand.fingers:  # moving while the simulated hand works it out
            for j in finger.joints:
                if busy or servos[j.id].profile is None:
                    servos[j.id].set("present_velocity", 1 if busy else 0)
        if not busy and self.sim.steps_done != self._version:
            self._report()
        drives = self._seen
        for i, finger in enumerate(self.hand.fingers):
            if self.sim.dropped and not busy:  # nothing stops it: it goes to its drives
                q = np.array([ticks_to_rad(drives[j.id], j.zero_ticks, j.direction)
                              for j in finger.joints])
            else:
                q = self._reported[i]
            for j, angle in zip(finger.joints, q, strict=True):
                servo = servos[j.id]
                pressing = servo.torque_on and not self.sim.dropped
                servo.set_present(position=rad_to_ticks(float(angle), j.zero_ticks, j.direction),
                                  current=servo.get("goal_current") if pressing else 0)
            roll = finger.tip_roll
            if roll is not None:
                servos[roll.id].set_present(position=rad_to_ticks(float(self._rolls[i]),
                                                                  roll.zero_ticks,
                                                                  roll.direction))

    def _move(self, drives: dict[int, int]) -> bool:
        """The fingers whose drives changed, as one command of the simulated hand, worked
        out on a thread of its own (tens of milliseconds: the bus keeps answering reads
        meanwhile, as servos do while they move). Whether it started."""
        centres = self.sim.centres
        moves: list[FingerMove | None] = []
        for i, finger in enumerate(self.hand.fingers):
            ids = [j.id for j in finger.joints]
            roll = finger.tip_roll
            turned = roll is not None and drives[roll.id] != self._seen.get(roll.id)
            if not turned and all(drives[k] == self._seen.get(k) for k in ids):
                moves.append(None)
                continue
            q = np.array([ticks_to_rad(drives[j.id], j.zero_ticks, j.direction)
                          for j in finger.joints])
            reach = kin.forward(finger, q)
            turn = 0.0
            if turned and roll is not None:
                turn = ticks_to_rad(drives[roll.id], roll.zero_ticks, roll.direction) \
                    - float(self._rolls[i])
            moves.append(FingerMove(dx=float(reach[0] - centres[i, 0]),
                                    dz=float(reach[2] - centres[i, 1]), roll=turn))
        if all(m is None for m in moves):
            return False
        self._worker = threading.Thread(target=self._step, args=(HandCommand(tuple(moves)),),
                                        name="hand-plant", daemon=True)
        self._worker.start()
        return True

    def _step(self, command: HandCommand) -> None:
        try:
            self.sim.command_hand(command)
            self.moves += 1
        except (ValueError, FirmwareError, ServiceError):
            self.refused += 1

    def _report(self) -> None:
        """Encoder values of what the simulated hand reads now (its noise included)."""
        readings, angles, self._rolls = self.sim.reported()
        self._reported = []
        for finger, reading, q in zip(self.hand.fingers, readings, angles, strict=True):
            ik = kin.inverse(finger, np.array([reading[0], 0.0, reading[1]]), q,
                             tolerance=1e-7, iterations=200)
            self._reported.append(ik.q if bool(ik.reachable) else q)
        self._version = self.sim.steps_done
