"""The emulator answers the e-Manual's published example packets byte for byte, and follows
its rules for access, ranges, EEPROM locking, status return level and broadcast."""

from __future__ import annotations

import pytest

from firmware_if import packets as pk
from sim_backend.clock import ManualClock
from sim_backend.emulator import EmulatedServo, ServoBus
from sim_backend.emulator.rawport import RawPort


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace("0x", "").replace(",", " "))


def w210(servo_id: int) -> EmulatedServo:
    """The e-Manual's examples use an XM430-W210: model 1030, firmware 38."""
    servo = EmulatedServo(servo_id)
    servo.mem[0:2] = (1030).to_bytes(2, "little")
    servo.mem[6] = 38
    return servo


@pytest.fixture
def bus():
    servos = [w210(1), w210(2)]
    with ServoBus(servos, clock=ManualClock(), honour_return_delay=False) as b:
        port = RawPort(b.port)
        yield b, port
        port.close()


def test_ping_example(bus):
    _, port = bus
    reply = port.exchange(h("FF FF FD 00 01 03 00 01 19 4E"), 14)
    assert reply == h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")


def test_broadcast_ping_example_both_servos_answer_in_id_order(bus):
    _, port = bus
    reply = port.exchange(h("FF FF FD 00 FE 03 00 01 31 42"), 28)
    assert reply == h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D"
                      "FF FF FD 00 02 07 00 55 00 06 04 26 6F 6D")


def test_read_example(bus):
    b, port = bus
    b.servos[1].set("present_position", 166)
    reply = port.exchange(h("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"), 15)
    assert reply == h("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")


def test_write_example_sets_goal_and_acknowledges(bus):
    b, port = bus
    reply = port.exchange(h("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"), 11)
    assert reply == h("FF FF FD 00 01 04 00 55 00 A1 0C")
    assert b.servos[1].get("goal_position") == 512


def test_reg_write_then_action_example(bus):
    b, port = bus
    reply = port.exchange(h("FF FF FD 00 01 09 00 04 68 00 C8 00 00 00 AE 8E"), 11)
    assert reply == h("FF FF FD 00 01 04 00 55 00 A1 0C")
    assert b.servos[1].get("goal_velocity") == 0
    assert b.servos[1].get("registered_instruction") == 1
    reply = port.exchange(h("FF FF FD 00 01 03 00 05 02 CE"), 11)
    assert reply == h("FF FF FD 00 01 04 00 55 00 A1 0C")
    assert b.servos[1].get("goal_velocity") == 200
    assert b.servos[1].get("registered_instruction") == 0


def test_action_without_reg_write_is_an_instruction_error(bus):
    _, port = bus
    reply = pk.parse(port.exchange(pk.packet(1, pk.INST_ACTION), 11))
    assert reply.params[0] == 0x02


def test_sync_read_example(bus):
    b, port = bus
    b.servos[1].set("present_position", 166)
    b.servos[2].set("present_position", 2079)
    reply = port.exchange(h("FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"), 30)
    assert reply == h("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0"
                      "FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE")


def test_sync_write_example_is_silent_and_applied(bus):
    b, port = bus
    port.send(h("FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"))
    assert b.wait_until(lambda: b.servos[2].get("goal_position") == 170)
    assert b.servos[1].get("goal_position") == 150
    assert port.receive(1, timeout=0.05) == b""


def test_bulk_read_example(bus):
    b, port = bus
    b.servos[1].set("present_input_voltage", 119)
    b.servos[2].set("present_temperature", 36)
    reply = port.exchange(h("FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05"), 25)
    assert reply == h("FF FF FD 00 01 06 00 55 00 77 00 C3 69"
                      "FF FF FD 00 02 05 00 55 00 24 8B A9")


def test_bulk_write_example(bus):
    b, port = bus
    b.servos[1].set("max_voltage_limit", 100)
    b.servos[2].set("temperature_limit", 70)
    port.send(h("FF FF FD 00 FE 10 00 93 01 20 00 02 00 A0 00 02 1F 00 01 00 50 B7 68"))
    assert b.wait_until(lambda: b.servos[2].get("temperature_limit") == 80)
    assert b.servos[1].get("max_voltage_limit") == 160


def test_fast_sync_read_example():
    servos = [w210(3), w210(7), w210(4)]
    for servo, value in zip(servos, (166, 2079, 1023), strict=True):
        servo.set("present_position", value)
    with ServoBus(servos, honour_return_delay=False) as b:
        port = RawPort(b.port)
        reply = port.exchange(h("FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2"), 32)
        port.close()
    assert reply == h("FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08"
                      "00 07 1F 08 00 00 16 CA 00 04 FF 03 00 00 D1 9E")


def test_factory_reset_example_keeps_id(bus):
    b, port = bus
    b.servos[1].set("return_delay_time", 0)
    reply = port.exchange(h("FF FF FD 00 01 04 00 06 01 A1 E6"), 11)
    assert reply == h("FF FF FD 00 01 04 00 55 00 A1 0C")
    # the servo answers, then resets: the bus applies it after the reply has gone out
    assert b.wait_until(lambda: b.servos[1].get("return_delay_time") == 250)
    assert b.servos[1].id == 1


def test_broadcast_factory_reset_all_is_refused(bus):
    b, port = bus
    b.servos[2].set("return_delay_time", 0)
    port.send(pk.packet(pk.BROADCAST_ID, pk.INST_FACTORY_RESET, b"\xff"))
    port.send(pk.packet(2, pk.INST_PING))
    assert len(port.receive(14)) == 14
    assert b.servos[2].get("return_delay_time") == 0


def test_reboot_example_clears_hardware_error_and_keeps_eeprom(bus):
    b, port = bus
    b.servos[1].set("return_delay_time", 3)
    b.inject_hardware_error(1, 0x20)
    ping = pk.parse(port.exchange(pk.packet(1, pk.INST_PING), 14))
    assert ping.params[0] & 0x80  # the alert bit
    reply = pk.parse(port.exchange(h("FF FF FD 00 01 03 00 08 2F 4E"), 11))
    assert reply.params == b"\x80"  # answered (alert still set), then rebooted
    assert b.wait_until(lambda: b.servos[1].get("hardware_error_status") == 0)
    assert b.servos[1].get("return_delay_time") == 3


def _write(port: RawPort, servo_id: int, address: int, data: bytes) -> int:
    reply = pk.parse(port.exchange(pk.packet(servo_id, pk.INST_WRITE,
                                             address.to_bytes(2, "little") + data), 11))
    return reply.params[0] & 0x7F


def test_write_rules(bus):
    b, port = bus
    assert _write(port, 1, 132, (5).to_bytes(4, "little")) == 7  # read-only
    assert _write(port, 1, 14, b"\x00") == 7  # undefined address
    assert _write(port, 1, 116, (5).to_bytes(2, "little")) == 5  # half of a 4-byte item
    assert _write(port, 1, 11, b"\x02") == 4  # operating mode 2 does not exist
    assert _write(port, 1, 64, b"\x02") == 4  # torque enable is 0 or 1
    assert _write(port, 1, 116, (5000).to_bytes(4, "little")) == 6  # beyond max position limit
    assert _write(port, 1, 38, (100).to_bytes(2, "little")) == 0
    assert _write(port, 1, 102, (200).to_bytes(2, "little", signed=True)) == 6  # > current limit
    assert _write(port, 1, 64, b"\x01") == 0
    assert _write(port, 1, 9, b"\x00") == 7  # EEPROM locked while torque is on
    assert _write(port, 1, 64, b"\x00") == 0
    assert _write(port, 1, 9, b"\x00") == 0
    assert b.servos[1].get("return_delay_time") == 0


def test_crc_error_is_reported(bus):
    _, port = bus
    bad = bytearray(pk.packet(1, pk.INST_READ, bytes([132, 0, 4, 0])))
    bad[-1] ^= 0xFF
    reply = pk.parse(port.exchange(bytes(bad), 11))
    assert reply.params[0] == 0x03


def test_status_return_level_zero_answers_only_ping(bus):
    b, port = bus
    b.servos[1].set("status_return_level", 0)
    port.send(pk.packet(1, pk.INST_READ, bytes([132, 0, 4, 0])))
    assert port.receive(1, timeout=0.05) == b""
    assert len(port.exchange(pk.packet(1, pk.INST_PING), 14)) == 14


def test_unstuffed_header_inside_a_packet_loses_the_packet(bus):
    b, port = bus
    body = bytes([20, 0]) + bytes([0xFF, 0xFF, 0xFD, 0xFF])  # homing offset -131073
    port.send(pk.packet(1, pk.INST_WRITE, body, stuffing=False))
    assert port.receive(1, timeout=0.1) == b""
    assert b.stats["resync"] == 1
    reply = pk.parse(port.exchange(pk.packet(1, pk.INST_WRITE, body), 11))
    assert reply.params[0] == 0
    assert b.servos[1].get("homing_offset") == -131073


def test_status_packets_are_byte_stuffed(bus):
    b, port = bus
    b.servos[1].set("present_current", -1)  # FF FF
    b.servos[1].set("present_velocity", 253)  # FD 00 00 00
    raw = port.exchange(pk.packet(1, pk.INST_READ, bytes([126, 0, 6, 0])), 18)
    assert b"\xff\xff\xfd\xfd" in raw
    assert pk.parse(raw).params[1:] == bytes([0xFF, 0xFF, 0xFD, 0, 0, 0])


def test_profile_follows_goal_on_the_servo_clock():
    clock = ManualClock()
    servo = EmulatedServo(1, position=0)
    with ServoBus([servo], clock=clock, honour_return_delay=False) as b:
        port = RawPort(b.port)
        assert _write(port, 1, 112, (100).to_bytes(4, "little")) == 0  # 100 x 0.229 rpm
        assert _write(port, 1, 64, b"\x01") == 0
        assert _write(port, 1, 116, (1000).to_bytes(4, "little")) == 0
        speed = 100 * 0.229 * 4096 / 60  # ticks per second
        clock.advance(0.5 * 1000 / speed)
        half = pk.parse(port.exchange(pk.packet(1, pk.INST_READ, bytes([122, 0, 1, 0])), 12))
        position = pk.parse(port.exchange(pk.packet(1, pk.INST_READ, bytes([132, 0, 4, 0])), 15))
        assert half.params[1] == 1  # moving
        assert abs(int.from_bytes(position.params[1:], "little") - 500) <= 1
        clock.advance(10.0)
        done = pk.parse(port.exchange(pk.packet(1, pk.INST_READ, bytes([132, 0, 4, 0])), 15))
        assert int.from_bytes(done.params[1:], "little") == 1000
        port.close()


def test_writing_the_id_moves_the_servo(bus):
    b, port = bus
    assert _write(port, 2, 7, b"\x09") == 0
    assert sorted(b.servos) == [1, 9]
    assert pk.parse(port.exchange(pk.packet(9, pk.INST_PING), 14)).id == 9
