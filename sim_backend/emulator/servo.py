"""One emulated X-series servo: its control table and how it answers reads and writes.

The rules are the e-Manual's: writes must cover whole items, read-only items and undefined
addresses give an Access Error, EEPROM items are locked while Torque Enable is 1, values
outside an item's range give a Data Range Error and goals beyond their limit item a Data
Limit Error. The goal is followed with the velocity/acceleration profile; a hardware error
turns torque off and sets the alert bit of every status packet until a reboot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_if.registers import (
    ALERT_BIT,
    CURRENT_BASED_POSITION,
    EXTENDED_RANGE,
    MODELS,
    OPERATING_MODES,
    TABLE_SIZE,
    TICKS_PER_REV,
    Register,
    by_name,
)

ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_RANGE, ERR_LENGTH, ERR_LIMIT, ERR_ACCESS = \
    1, 2, 3, 4, 5, 6, 7
_INDIRECT_DATA = range(224, 252)


@dataclass
class Profile:
    """Motion from `start` to `goal` ticks beginning at `t0_ns` (velocity/acceleration in
    ticks/s and ticks/s^2; 0 means unlimited, as in the e-Manual)."""

    start: float
    goal: float
    t0_ns: int
    velocity: float
    acceleration: float

    def at(self, now_ns: int) -> tuple[float, float, bool]:
        """(position, velocity, still moving) at `now_ns`."""
        distance = self.goal - self.start
        sign = 1.0 if distance >= 0 else -1.0
        d = abs(distance)
        t = max(0.0, (now_ns - self.t0_ns) * 1e-9)
        v, a = self.velocity, self.acceleration
        if d == 0 or v <= 0:
            return self.goal, 0.0, False
        if a <= 0:  # constant velocity
            if t * v >= d:
                return self.goal, 0.0, False
            return self.start + sign * v * t, sign * v, True
        t_acc = v / a
        if a * t_acc * t_acc >= d:  # triangular profile
            t_acc = math.sqrt(d / a)
            v = a * t_acc
            t_flat = 0.0
        else:
            t_flat = (d - a * t_acc * t_acc) / v
        total = 2 * t_acc + t_flat
        if t >= total:
            return self.goal, 0.0, False
        if t < t_acc:
            s, vel = 0.5 * a * t * t, a * t
        elif t < t_acc + t_flat:
            s, vel = 0.5 * a * t_acc * t_acc + v * (t - t_acc), v
        else:
            r = total - t
            s, vel = d - 0.5 * a * r * r, a * r
        return self.start + sign * s, sign * vel, True


class EmulatedServo:
    """Control table and behaviour of one servo (XM430-W350 by default)."""

    def __init__(self, servo_id: int, model: str = "XM430-W350", *,
                 firmware_version: int | None = None, position: int = 2048) -> None:
        self.model_number, self.table_def = MODELS[model]
        self.model = model
        self._by_name = by_name(self.table_def)
        self._owner: dict[int, Register] = {}
        for r in self.table_def:
            for a in range(r.address, r.address + r.size):
                self._owner[a] = r
        self.mem = bytearray(TABLE_SIZE)
        self._firmware = firmware_version
        self._load_defaults(keep=())
        self.set("id", servo_id)
        self.registered: tuple[int, bytes] | None = None
        self.drive = float(position)
        """Where the motor is driving the joint (ticks); the plant may hold it elsewhere."""
        self.profile: Profile | None = None
        self.set_present(position=position)

    # -- table ---------------------------------------------------------------------------
    def _load_defaults(self, keep: tuple[str, ...]) -> None:
        kept = {name: self.get(name) for name in keep}
        for r in self.table_def:
            self.mem[r.address:r.address + r.size] = r.encode(r.initial)
        self.mem[0:2] = self.model_number.to_bytes(2, "little")
        if self._firmware is not None:
            self.mem[6] = self._firmware
        for name, value in kept.items():
            self.set(name, value)

    def reg(self, name: str) -> Register:
        """The register called `name` (KeyError if the model has none): a dict lookup, as
        every packet reads and writes a dozen of them."""
        return self._by_name[name]

    def get(self, name: str) -> int:
        r = self.reg(name)
        return r.decode(bytes(self.mem[r.address:r.address + r.size]))

    def set(self, name: str, value: int) -> None:
        """Set an item directly (emulator side: no access checks)."""
        r = self.reg(name)
        self.mem[r.address:r.address + r.size] = r.encode(value)

    @property
    def id(self) -> int:
        return self.mem[7]

    @property
    def torque_on(self) -> bool:
        return bool(self.mem[64])

    @property
    def firmware_version(self) -> int:
        return self.mem[6]

    def error_byte(self, number: int = 0) -> int:
        return number | (ALERT_BIT if self.mem[70] else 0)

    # -- instructions ----------------------------------------------------------------------
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error number, data) for a Read of `length` bytes at `address`."""
        if length < 1 or address + length > TABLE_SIZE:
            return ERR_ACCESS, b""
        data = bytearray(self.mem[address:address + length])
        for a in range(address, address + length):
            if a in _INDIRECT_DATA:
                target = self.get(f"indirect_address_{a - 223}")
                if target not in _INDIRECT_DATA:
                    data[a - address] = self.mem[target]
        return 0, bytes(data)

    def check_write(self, address: int, data: bytes) -> int:
        """Error number a Write of `data` at `address` would get (0: it is allowed)."""
        end = address + len(data)
        if not data or end > TABLE_SIZE:
            return ERR_ACCESS
        a = address
        while a < end:
            r = self._owner.get(a)
            if r is None or r.access != "RW":
                return ERR_ACCESS
            if r.address != a or a + r.size > end:
                return ERR_LENGTH
            if r.eeprom and self.torque_on:
                return ERR_ACCESS
            value = r.decode(bytes(data[a - address:a - address + r.size]))
            if not r.lo <= value <= r.hi or (r.name == "operating_mode"
                                             and value not in OPERATING_MODES):
                return ERR_RANGE
            if r.limit and not self._within_limit(r, value):
                return ERR_LIMIT
            a += r.size
        return 0

    def _within_limit(self, r: Register, value: int) -> bool:
        if r.limit == "position_limit":
            if self.get("operating_mode") == 3:
                return self.get("min_position_limit") <= value <= self.get("max_position_limit")
            return -EXTENDED_RANGE <= value <= EXTENDED_RANGE
        return abs(value) <= self.get(r.limit)

    def write(self, address: int, data: bytes, now_ns: int) -> int:
        """Apply a Write; returns the error number (nothing changes on error)."""
        error = self.check_write(address, data)
        if error:
            return error
        torque_before = self.torque_on
        for i, byte in enumerate(data):
            a = address + i
            if a in _INDIRECT_DATA:
                target = self.get(f"indirect_address_{a - 223}")
                if target not in _INDIRECT_DATA:
                    if self._owner.get(target) is None or self._owner[target].access != "RW":
                        continue
                    self.mem[target] = byte
                    continue
            self.mem[a] = byte
        if self.mem[70] and self.torque_on:  # a latched hardware error keeps torque off
            self.mem[64] = 0
            return ERR_RESULT_FAIL
        goal_written = address <= 116 < address + len(data)
        if torque_before and not self.torque_on:
            self.on_torque_change()
        elif self.torque_on and not torque_before and not goal_written:
            self.set("goal_position", int(round(self.drive)))  # hold where it is
        if goal_written and self.torque_on:
            self._start_profile(now_ns)
        return 0

    def _start_profile(self, now_ns: int) -> None:
        if not self.torque_on:
            return
        unit_v = 0.229 * TICKS_PER_REV / 60.0
        unit_a = 214.577 * TICKS_PER_REV / 3600.0
        self.profile = Profile(self.drive, float(self.get("goal_position")), now_ns,
                               self.get("profile_velocity") * unit_v,
                               self.get("profile_acceleration") * unit_a)

    def advance(self, now_ns: int) -> bool:
        """Move the drive along its profile; returns whether it is still moving."""
        if self.profile is None or not self.torque_on:
            return False
        self.drive, velocity, moving = self.profile.at(now_ns)
        self.mem[122] = int(moving)
        self.mem[123] = (0 if moving else 1) | (2 if moving else 0)
        self.set("present_velocity", int(round(velocity * 60.0 / (0.229 * TICKS_PER_REV))))
        self.set("position_trajectory", int(round(self.drive)))
        self.set_present(position=self.drive)  # a plant, if any, overrides this
        if not moving:
            self.profile = None
        return moving

    def set_present(self, *, position: float | None = None, current: int | None = None) -> None:
        if position is not None:
            self.set("present_position", int(round(position)))
        if current is not None:
            limit = self.get("current_limit")
            self.set("present_current", max(-limit, min(limit, int(current))))

    def on_torque_change(self) -> None:
        if not self.torque_on:
            self.profile = None
            self.set("goal_position", int(round(self.drive)))

    def reboot(self) -> None:
        """Power cycle: RAM back to defaults, EEPROM kept, the hardware error cleared."""
        eeprom = {r.name: self.get(r.name) for r in self.table_def if r.eeprom and r.access == "RW"}
        position = self.get("present_position")
        self._load_defaults(keep=())
        for name, value in eeprom.items():
            self.set(name, value)
        self.registered = None
        self.profile = None
        self.drive = float(position % TICKS_PER_REV if self.get("operating_mode") != 4
                           else position)
        self.set_present(position=self.drive)

    def factory_reset(self, option: int) -> None:
        keep = {0xFF: (), 0x01: ("id",), 0x02: ("id", "baud_rate")}.get(option, ("id",))
        self._load_defaults(keep=keep)
        self.registered = None
        self.profile = None
        self.set_present(position=self.drive)

    def clear_multi_turn(self) -> int:
        if self.profile is not None:
            return ERR_RESULT_FAIL
        self.drive = float(int(self.drive) % TICKS_PER_REV)
        self.set_present(position=self.drive)
        return 0

    @property
    def compliant(self) -> bool:
        """Whether the servo limits its current (operating mode 5), so contact can stop it."""
        return self.get("operating_mode") == CURRENT_BASED_POSITION
