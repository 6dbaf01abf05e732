"""Fault injection on the emulated bus, seen from the host side of the pty."""

from __future__ import annotations

import dataclasses

import pytest

from firmware_if import packets as pk
from sim_backend.emulator import EmulatedServo, ServoBus
from sim_backend.emulator.drills import DrillError, drill
from sim_backend.emulator.rawport import RawPort

PING = pk.packet(1, pk.INST_PING)


@pytest.fixture
def rig():
    with ServoBus([EmulatedServo(1), EmulatedServo(2)], honour_return_delay=False) as bus:
        port = RawPort(bus.port)
        yield bus, port
        port.close()


def test_drop_swallows_exactly_that_many_replies(rig):
    bus, port = rig
    bus.fault(1).drop = 2
    assert port.exchange(PING, 14, timeout=0.05) == b""
    assert port.exchange(PING, 14, timeout=0.05) == b""
    assert pk.parse(port.exchange(PING, 14)).id == 1
    assert bus.stats["dropped"] == 2


def test_corrupt_breaks_only_the_crc(rig):
    bus, port = rig
    bus.fault(1).corrupt = 1
    raw = port.exchange(PING, 14)
    assert len(raw) == 14
    with pytest.raises(pk.PacketError, match="CRC"):
        pk.parse(raw)
    assert pk.parse(port.exchange(PING, 14)).params == bytes([0, 0xFC, 0x03, 46])


def test_late_reply_arrives_after_the_delay(rig):
    bus, port = rig
    bus.fault(1).late_s = 0.2
    assert port.exchange(PING, 14, timeout=0.05) == b""
    assert pk.parse(port.receive(14, timeout=2.0)).id == 1


def test_mute_servo_is_absent_from_sync_and_fast_sync_reads(rig):
    bus, port = rig
    bus.fault(1).mute = True
    sync = port.exchange(pk.packet(0xFE, pk.INST_SYNC_READ, bytes([132, 0, 4, 0, 1, 2])), 30,
                         timeout=0.2)
    assert len(sync) == 15 and pk.parse(sync).id == 2
    fast = port.exchange(pk.packet(0xFE, pk.INST_FAST_SYNC_READ, bytes([132, 0, 4, 0, 1, 2])),
                         24, timeout=0.1)
    assert fast == b""  # the first servo never starts the shared packet


def test_hardware_error_sets_the_alert_bit_and_drops_torque(rig):
    bus, port = rig
    bus.servos[1].set("torque_enable", 1)
    bus.inject_hardware_error(1, 0x04)  # overheating: in the default Shutdown mask
    reply = pk.parse(port.exchange(pk.packet(1, pk.INST_READ, bytes([70, 0, 1, 0])), 12))
    assert reply.params == bytes([0x80, 0x04])
    assert not bus.servos[1].torque_on
    torque_on = pk.packet(1, pk.INST_WRITE, bytes([64, 0, 1]))
    assert pk.parse(port.exchange(torque_on, 11)).params == bytes([0x81])  # result fail
    assert not bus.servos[1].torque_on


def _snapshot(bus: ServoBus) -> tuple:
    faults = {sid: dataclasses.astuple(plan) for sid, plan in bus.faults.items()}
    registers = {sid: (s.get("torque_enable"), s.get("hardware_error_status"))
                 for sid, s in bus.servos.items()}
    return faults, registers


@pytest.mark.parametrize("line, message", [
    ("unplug 1", "unknown drill 'unplug'"),
    ("mute", "'mute' takes 1 value"),
    ("mute 7", "no servo 7 on this bus"),
    ("mute one", "whole number"),
    ("drop 1 -2", "whole count of replies in 0..1000000"),
    ("drop 1 1e9", "whole count of replies"),  # it said ">= 0" of a count too large
    ("corrupt 1 2.5", "whole count of replies"),
    ("late 1 soon", "seconds in 0..10"),
    ("error 1 overload,fire", "unknown hardware error 'fire'"),
])
def test_a_bad_drill_says_why_and_changes_nothing(rig, line, message):
    bus, _ = rig
    before = _snapshot(bus)
    with pytest.raises(DrillError, match=message):
        drill(bus, line)
    assert _snapshot(bus) == before


def test_drills_make_the_faults_they_name(rig):
    bus, port = rig
    bus.servos[2].set("torque_enable", 1)
    assert drill(bus, "mute 1") == "ok: mute 1"
    assert port.exchange(PING, 14, timeout=0.05) == b""
    drill(bus, "unmute 1")
    assert pk.parse(port.exchange(PING, 14)).id == 1
    drill(bus, "error 2 overload,overheating")
    assert bus.servos[2].get("hardware_error_status") == (1 << 5) | (1 << 2)
    assert bus.servos[2].get("torque_enable") == 0  # both are shutdown errors by default
    drill(bus, "reboot 2")
    assert bus.servos[2].get("hardware_error_status") == 0
    drill(bus, "late 1 0.2")
    drill(bus, "clear 1")
    assert 1 not in bus.faults and "reboot ID" in drill(bus, "help")
