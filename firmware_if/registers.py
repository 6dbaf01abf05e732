"""The X-series control table as data (Protocol 2.0), with paired tick <-> SI conversions.

Declared once, from the ROBOTIS e-Manual page of the XM430-W350 (model number 1020): address,
size, access, EEPROM or RAM, factory default and the raw range a write must respect. The bus
driver, the emulator and `haptic bus check` all read this table; nothing above it sees ticks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TICKS_PER_REV = 4096
RAD_PER_TICK = 2 * math.pi / TICKS_PER_REV
RPM_UNIT = 0.229
"""Velocity unit of the X series, rev/min per tick."""
RAD_S_PER_VEL = RPM_UNIT * 2 * math.pi / 60
AMP_PER_CURRENT = 2.69e-3
"""Current unit of the XM430, amperes per tick."""
POSITION_CENTRE = 2048
"""Tick at the middle of one turn: the default register value of joint angle 0."""
EXTENDED_RANGE = 1_048_575
"""Goal Position range in extended and current-based position modes (+-256 turns)."""

BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
"""Baud Rate(8) register value -> bits per second."""
BAUD_REGISTER = {bps: value for value, bps in BAUD_RATES.items()}
"""Bits per second -> Baud Rate(8) register value."""
OPERATING_MODES = {0: "current", 1: "velocity", 3: "position", 4: "extended position",
                   5: "current-based position", 16: "pwm"}
CURRENT_BASED_POSITION = 5

HARDWARE_ERRORS = {0: "input voltage error", 2: "overheating error",
                   3: "motor encoder error", 4: "electrical shock error",
                   5: "overload error"}
"""Hardware Error Status(70) bit -> meaning (e-Manual, Shutdown(63))."""

STATUS_ERRORS = {1: "result fail", 2: "instruction error", 3: "CRC error",
                 4: "data range error", 5: "data length error", 6: "data limit error",
                 7: "access error"}
"""Error field of a status packet (bits 0-6) -> meaning; bit 7 is the hardware alert."""
ALERT_BIT = 0x80


@dataclass(frozen=True)
class Register:
    """One control-table item."""

    name: str
    address: int
    size: int
    access: str
    """'R' read-only or 'RW'."""
    eeprom: bool
    initial: int
    lo: int
    hi: int
    """Raw range a write must respect (Data Range Error outside it)."""
    limit: str | None = None
    """Name of the register whose value bounds writes (Data Limit Error beyond it)."""

    @property
    def signed(self) -> bool:
        return self.lo < 0

    def encode(self, value: int) -> bytes:
        return int(value).to_bytes(self.size, "little", signed=self.signed)

    def decode(self, raw: bytes) -> int:
        return int.from_bytes(raw[: self.size], "little", signed=self.signed)


def _r(name: str, address: int, size: int, access: str, initial: int, lo: int = 0,
       hi: int | None = None, limit: str | None = None) -> Register:
    if hi is None:
        hi = (1 << (8 * size)) - 1
    return Register(name, address, size, access, address < 64, initial, lo, hi, limit)


XM430_W350: tuple[Register, ...] = (
    _r("model_number", 0, 2, "R", 1020),
    _r("model_information", 2, 4, "R", 0),
    _r("firmware_version", 6, 1, "R", 46),
    _r("id", 7, 1, "RW", 1, 0, 252),
    _r("baud_rate", 8, 1, "RW", 1, 0, 7),
    _r("return_delay_time", 9, 1, "RW", 250, 0, 254),
    _r("drive_mode", 10, 1, "RW", 0, 0, 13),
    _r("operating_mode", 11, 1, "RW", 3, 0, 16),
    _r("secondary_id", 12, 1, "RW", 255, 0, 255),
    _r("protocol_type", 13, 1, "RW", 2, 1, 2),
    _r("homing_offset", 20, 4, "RW", 0, -1_044_479, 1_044_479),
    _r("moving_threshold", 24, 4, "RW", 10, 0, 1023),
    _r("temperature_limit", 31, 1, "RW", 80, 0, 100),
    _r("max_voltage_limit", 32, 2, "RW", 160, 95, 160),
    _r("min_voltage_limit", 34, 2, "RW", 95, 95, 160),
    _r("pwm_limit", 36, 2, "RW", 885, 0, 885),
    _r("current_limit", 38, 2, "RW", 1193, 0, 1193),
    _r("acceleration_limit", 40, 4, "RW", 32767, 0, 32767),
    _r("velocity_limit", 44, 4, "RW", 350, 0, 1023),
    _r("max_position_limit", 48, 4, "RW", 4095, 0, 4095),
    _r("min_position_limit", 52, 4, "RW", 0, 0, 4095),
    _r("shutdown", 63, 1, "RW", 52, 0, 255),
    _r("torque_enable", 64, 1, "RW", 0, 0, 1),
    _r("led", 65, 1, "RW", 0, 0, 1),
    _r("status_return_level", 68, 1, "RW", 2, 0, 2),
    _r("registered_instruction", 69, 1, "R", 0),
    _r("hardware_error_status", 70, 1, "R", 0),
    _r("velocity_i_gain", 76, 2, "RW", 1920, 0, 16383),
    _r("velocity_p_gain", 78, 2, "RW", 100, 0, 16383),
    _r("position_d_gain", 80, 2, "RW", 0, 0, 16383),
    _r("position_i_gain", 82, 2, "RW", 0, 0, 16383),
    _r("position_p_gain", 84, 2, "RW", 800, 0, 16383),
    _r("feedforward_2nd_gain", 88, 2, "RW", 0, 0, 16383),
    _r("feedforward_1st_gain", 90, 2, "RW", 0, 0, 16383),
    _r("bus_watchdog", 98, 1, "RW", 0, 0, 127),
    _r("goal_pwm", 100, 2, "RW", 0, -885, 885, limit="pwm_limit"),
    _r("goal_current", 102, 2, "RW", 0, -1193, 1193, limit="current_limit"),
    _r("goal_velocity", 104, 4, "RW", 0, -1023, 1023, limit="velocity_limit"),
    _r("profile_acceleration", 108, 4, "RW", 0, 0, 32767),
    _r("profile_velocity", 112, 4, "RW", 0, 0, 32767),
    _r("goal_position", 116, 4, "RW", 0, -EXTENDED_RANGE, EXTENDED_RANGE,
       limit="position_limit"),
    _r("realtime_tick", 120, 2, "R", 0, 0, 32767),
    _r("moving", 122, 1, "R", 0),
    _r("moving_status", 123, 1, "R", 0),
    _r("present_pwm", 124, 2, "R", 0, -885, 885),
    _r("present_current", 126, 2, "R", 0, -1193, 1193),
    _r("present_velocity", 128, 4, "R", 0, -(1 << 31), (1 << 31) - 1),
    _r("present_position", 132, 4, "R", 0, -(1 << 31), (1 << 31) - 1),
    _r("velocity_trajectory", 136, 4, "R", 0, -(1 << 31), (1 << 31) - 1),
    _r("position_trajectory", 140, 4, "R", 0, -(1 << 31), (1 << 31) - 1),
    _r("present_input_voltage", 144, 2, "R", 120),
    _r("present_temperature", 146, 1, "R", 30),
    *(_r(f"indirect_address_{i + 1}", 168 + 2 * i, 2, "RW", 224 + i, 64, 661)
      for i in range(28)),
    *(_r(f"indirect_data_{i + 1}", 224 + i, 1, "RW", 0) for i in range(28)),
)
"""XM430-W350 control table (firmware 46: Fast Sync/Bulk Read supported from v45)."""

MODELS: dict[str, tuple[int, tuple[Register, ...]]] = {"XM430-W350": (1020, XM430_W350)}
"""Model name -> (model number, control table)."""

NEWTON_METRES_PER_AMP = {"XM430-W350": 4.1 / 2.3}
"""Output torque per ampere of motor current (e-Manual: 4.1 N m stall torque at 2.3 A,
12 V): how hard a joint pushes at its goal-current bound in current-based position mode."""

TABLE_SIZE = 662


def by_name(table: tuple[Register, ...] = XM430_W350) -> dict[str, Register]:
    return {r.name: r for r in table}


REG = by_name()
"""The XM430-W350 registers by name: REG['present_position'].address == 132."""

SYNC_READ_START = REG["realtime_tick"].address
SYNC_READ_LENGTH = 16
"""One cycle reads Realtime Tick through Present Position (120..135) in one block: the
current, velocity and position, and the servo's clock, which tells a late reply to an
earlier cycle from this one's (`reply_age`)."""


# -- conversions (pure; ticks are raw register values) ---------------------------------------
def ticks_to_rad(ticks: int | float, zero: int = POSITION_CENTRE, direction: int = 1) -> float:
    """Joint angle in radians from a position register value."""
    return direction * (ticks - zero) * RAD_PER_TICK


def rad_to_ticks(angle: float, zero: int = POSITION_CENTRE, direction: int = 1) -> int:
    """Position register value nearest to a joint angle in radians."""
    return int(round(zero + direction * angle / RAD_PER_TICK))


def rad_s_to_velocity(rad_s: float) -> int:
    return int(round(abs(rad_s) / RAD_S_PER_VEL))


def amp_to_current(amp: float) -> int:
    return int(round(amp / AMP_PER_CURRENT))


def describe_hardware_error(bits: int) -> str:
    """Hardware Error Status bits in words ('' when none)."""
    names = [text for bit, text in HARDWARE_ERRORS.items() if bits & (1 << bit)]
    return ", ".join(names)


def describe_status_error(error: int) -> str:
    """The error byte of a status packet in words ('' when none)."""
    parts = []
    if error & ALERT_BIT:
        parts.append("hardware alert (read Hardware Error Status)")
    number = error & 0x7F
    if number:
        parts.append(STATUS_ERRORS.get(number, f"unknown error {number}"))
    return ", ".join(parts)
