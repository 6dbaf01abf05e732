"""Hardware in the loop: the simulated surface stops the emulated finger where it touches.

Each servo drives its joint towards its goal; the plant puts the fingertip centre where the
drives want it unless the contact surface (paper Eq. 7, the same lookup the simulated finger
uses) is higher there, in which case the centre rests on the surface and the joints report
the posture that reaches it, with the servos at their current bound. The map's edges are
walls: a motion that would leave the map stalls where it is. The hand frame is the finger's
own: its home centre sits above the hidden start (x, y) and is turned by the hidden heading.
"""

from __future__ import annotations

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.hand import Hand, joint_ticks
from firmware_if.registers import BAUD_REGISTER, rad_to_ticks, ticks_to_rad
from service.localization.surface import ContactSurface, HeightMap, contact_surface
from sim_backend.emulator.bus import Plant
from sim_backend.emulator.servo import EmulatedServo


class FingerPlant:
    """Couples the emulated servos of `hand` to a surface (see module docstring)."""

    def __init__(self, hand: Hand, world: HeightMap, start: tuple[float, float, float], *,
                 clearance: float = 0.005) -> None:
        self.hand = hand
        self.surface: ContactSurface = contact_surface(world, hand.radius)
        self.start = tuple(float(v) for v in start)
        self.home_q = np.asarray(hand.home, dtype=np.float64)
        self.home_centre = kin.forward(hand, self.home_q)
        x0, y0, _ = self.start
        if not bool(world.inside(np.array(x0), np.array(y0))):
            raise ValueError(f"plant start ({x0:.4g}, {y0:.4g}) m lies outside the map")
        self.z_offset = float(self.surface.height(x0, y0)) - (self.home_centre[2] - clearance)
        """Map z minus hand z, chosen so the home posture hovers `clearance` above contact."""
        self._cache: dict[tuple[int, ...], tuple[np.ndarray, bool]] = {}
        self._actual_q = self.home_q.copy()
        self._roll = 0.0
        self.in_contact = False
        self.jams = 0
        """Motions stopped because the contact posture lies beyond a joint limit."""
        self.walls = 0
        """Motions stopped at the map's edge."""

    def home_ticks(self) -> dict[int, int]:
        """Register values of the home posture (where the servos power up)."""
        return joint_ticks(self.hand.joints, self.home_q)

    def to_map(self, centre: np.ndarray) -> tuple[float, float]:
        """Hand-frame centre -> map (x, y)."""
        x0, y0, heading = self.start
        dx, dy = centre[0] - self.home_centre[0], centre[1] - self.home_centre[1]
        c, s = np.cos(heading), np.sin(heading)
        return x0 + c * dx - s * dy, y0 + s * dx + c * dy

    def contact_height(self, centre: np.ndarray) -> float | None:
        """Hand-frame z the centre rests at over this point, or None off the map."""
        mx, my = self.to_map(centre)
        if not bool(self.surface.map.inside(np.array(mx), np.array(my))):
            return None
        return float(self.surface.height(mx, my)) - self.z_offset

    def settle(self, q_drive: np.ndarray) -> tuple[np.ndarray, bool]:
        """(joint angles the finger ends at, in contact) for drives at `q_drive`."""
        centre = kin.forward(self.hand, q_drive)
        height = self.contact_height(centre)
        at_wall = height is None
        if at_wall:
            # a wall: the finger stays where it was along the surface, and slides down the
            # wall to the surface or the drives' height (held in the air where it met the
            # wall, it reported a reading 15 mm above the surface as a contact)
            self.walls += 1
            drive_z = centre[2]
            centre = kin.forward(self.hand, self._actual_q)
            centre[2] = drive_z
            height = self.contact_height(centre)
            if height is None:
                return self._actual_q.copy(), True
            q_drive = self._actual_q
        if centre[2] >= height:
            if at_wall:  # along the wall, above the surface: the drives' height
                result = kin.inverse(self.hand, centre, q_drive, tolerance=1e-7)
                return (result.q, False) if bool(result.reachable) else (q_drive.copy(), True)
            return q_drive, False
        target = np.array([centre[0], centre[1], height])
        result = kin.inverse(self.hand, target, q_drive, tolerance=1e-7)
        if not bool(result.reachable):
            # The arm cannot rest on the surface here (a joint limit): it jams before it
            # could push the tip into the surface, so it stays where it was.
            self.jams += 1
            return self._actual_q.copy(), True
        return result.q, True

    def update(self, servos: dict[int, EmulatedServo]) -> None:
        joints = self.hand.joints
        if any(j.id not in servos for j in joints):
            return
        drive_ticks = tuple(int(round(servos[j.id].drive)) for j in joints)
        cached = self._cache.get(drive_ticks)
        if cached is None:
            q_drive = np.array([ticks_to_rad(t, j.zero_ticks, j.direction)
                                for t, j in zip(drive_ticks, joints, strict=True)])
            held_before = self.jams + self.walls
            cached = self.settle(q_drive)
            if self.jams + self.walls == held_before:  # a held posture depends on history
                if len(self._cache) > 4096:
                    self._cache.clear()
                self._cache[drive_ticks] = cached
        q, contact = cached
        before = kin.forward(self.hand, self._actual_q)
        after = kin.forward(self.hand, q)
        self._roll += float(np.hypot(*(after[:2] - before[:2]))) / self.hand.radius
        self._actual_q = np.asarray(q)
        self.in_contact = contact
        for j, angle in zip(joints, q, strict=True):
            servo = servos[j.id]
            current = servo.get("goal_current") if contact and servo.torque_on else 0
            servo.set_present(position=rad_to_ticks(angle, j.zero_ticks, j.direction),
                              current=current)
        roll = self.hand.tip_roll
        if roll is not None and roll.id in servos:
            servos[roll.id].set_present(position=rad_to_ticks(self._roll, roll.zero_ticks,
                                                              roll.direction))


def hand_bus_servos(hand: Hand, plant: Plant | None = None) -> list[EmulatedServo]:
    """One emulated servo per joint of every finger of `hand` (and each tip roll), powered
    up where the plant has them (else at home), all on one bus."""
    if plant is not None:
        home = plant.home_ticks()
    else:
        home = {}
        for finger in hand.fingers:
            home.update(joint_ticks(finger.joints, finger.home))
    servos = []
    for finger in hand.fingers:
        servos += [EmulatedServo(j.id, j.model, position=home[j.id]) for j in finger.joints]
        roll = finger.tip_roll
        if roll is not None:
            servos.append(EmulatedServo(roll.id, position=home.get(roll.id, roll.zero_ticks)))
    baud = BAUD_REGISTER[hand.baud]
    for servo in servos:
        servo.set("baud_rate", baud)  # as the lab set them up for this hand
    return servos
