"""The control table as data: the e-Manual's key facts, no overlaps, exact conversions."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from firmware_if import registers as r


def test_key_items_of_the_xm430_w350():
    reg = r.REG
    assert reg["model_number"].initial == 1020
    assert (reg["operating_mode"].address, reg["operating_mode"].size) == (11, 1)
    assert (reg["torque_enable"].address, reg["torque_enable"].eeprom) == (64, False)
    assert (reg["hardware_error_status"].address, reg["hardware_error_status"].access) == (70, "R")
    assert (reg["goal_position"].address, reg["goal_position"].size) == (116, 4)
    assert (reg["present_position"].address, reg["present_position"].size) == (132, 4)
    assert reg["return_delay_time"].eeprom and reg["return_delay_time"].initial == 250
    assert r.SYNC_READ_START == 120 and r.SYNC_READ_LENGTH == 16


def test_items_do_not_overlap():
    owned: dict[int, str] = {}
    for item in r.XM430_W350:
        for a in range(item.address, item.address + item.size):
            assert a not in owned, f"{item.name} overlaps {owned.get(a)}"
            owned[a] = item.name
        assert item.lo <= item.initial <= item.hi or item.name.startswith("indirect")


@given(st.floats(-math.pi, math.pi), st.integers(0, 4095), st.sampled_from([1, -1]))
def test_ticks_round_trip_within_half_a_tick(angle, zero, direction):
    ticks = r.rad_to_ticks(angle, zero, direction)
    assert abs(r.ticks_to_rad(ticks, zero, direction) - angle) <= r.RAD_PER_TICK / 2 + 1e-12


def test_signed_items_encode_negative_values():
    item = r.REG["present_velocity"]
    assert item.encode(-3) == bytes([0xFD, 0xFF, 0xFF, 0xFF])
    assert item.decode(item.encode(-3)) == -3


def test_error_descriptions():
    assert r.describe_hardware_error(0b100100) == "overheating error, overload error"
    assert r.describe_status_error(0x84) == "hardware alert (read Hardware Error Status), " \
                                            "data range error"
