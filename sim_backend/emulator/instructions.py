"""The instructions of Protocol 2.0 as the e-Manual specifies them, one function each.

Each takes the bus (for its servos, faults and replies), the checked packet and the bus
clock's time; the table at the end maps instruction codes to them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from firmware_if import packets as pk
from sim_backend.emulator.servo import ERR_INSTRUCTION, ERR_RANGE, EmulatedServo

if TYPE_CHECKING:
    from sim_backend.emulator.bus import ServoBus


def ping(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    for servo in bus.targets(packet.id):
        params = servo.get("model_number").to_bytes(2, "little") + \
            bytes([servo.firmware_version])
        bus.reply(servo, servo.error_byte(), params)


def read(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    servo = bus.servos.get(packet.id)
    if servo is None or packet.id == pk.BROADCAST_ID:
        return
    if len(packet.params) != 4:
        bus.reply(servo, servo.error_byte(5))
        return
    address, length = _u16(packet.params, 0), _u16(packet.params, 2)
    error, data = servo.read(address, length)
    if bus.wants_reply(servo, packet, True):
        bus.reply(servo, servo.error_byte(error), data)


def write_inst(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    if len(packet.params) < 3:
        return
    address, data = _u16(packet.params, 0), packet.params[2:]
    for servo in bus.targets(packet.id):
        old_id = servo.id
        error = servo.write(address, data, now)
        _rekey(bus, old_id, servo)  # before the reply: whoever has it finds the servo moved
        if bus.wants_reply(servo, packet, False):
            # sent after the write: an ID change answers with the new id
            bus.reply(servo, servo.error_byte(error))


def _rekey(bus: ServoBus, old_id: int, servo: EmulatedServo) -> None:
    """Follow a servo whose ID was written."""
    if servo.id != old_id and bus.servos.get(old_id) is servo:
        del bus.servos[old_id]
        bus.servos[servo.id] = servo


def reg_write(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    address, data = _u16(packet.params, 0), packet.params[2:]
    for servo in bus.targets(packet.id):
        error = servo.check_write(address, data)
        if not error:
            servo.registered = (address, bytes(data))
            servo.set("registered_instruction", 1)
        if bus.wants_reply(servo, packet, False):
            bus.reply(servo, servo.error_byte(error))


def action(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    for servo in bus.targets(packet.id):
        error = ERR_INSTRUCTION
        if servo.registered is not None:
            error = servo.write(*servo.registered, now)
            servo.registered = None
            servo.set("registered_instruction", 0)
        if bus.wants_reply(servo, packet, False):
            bus.reply(servo, servo.error_byte(error))


def factory_reset(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    option = packet.params[0] if packet.params else 0xFF
    if packet.id == pk.BROADCAST_ID and option == 0xFF:
        return  # refused by firmware 42+, per the e-Manual
    for servo in bus.targets(packet.id):
        old_id = servo.id
        reply = bus.wants_reply(servo, packet, False)
        if reply:
            bus.reply(servo, servo.error_byte())
        servo.factory_reset(option)
        _rekey(bus, old_id, servo)


def reboot(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    for servo in bus.targets(packet.id):
        if bus.wants_reply(servo, packet, False):
            bus.reply(servo, servo.error_byte())
        servo.reboot()


def clear(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    for servo in bus.targets(packet.id):
        ok = packet.params[:5] == bytes([0x01, 0x44, 0x58, 0x4C, 0x22])
        error = servo.clear_multi_turn() if ok else ERR_RANGE
        if bus.wants_reply(servo, packet, False):
            bus.reply(servo, servo.error_byte(error))


def sync_read(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    if packet.id != pk.BROADCAST_ID or len(packet.params) < 5:
        return
    address, length = _u16(packet.params, 0), _u16(packet.params, 2)
    for sid in packet.params[4:]:
        servo = bus.servos.get(sid)
        if servo is not None and servo.get("status_return_level") >= 1:
            error, data = servo.read(address, length)
            bus.reply(servo, servo.error_byte(error), data)


def bulk_read(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    for sid, address, length in _bulk_items(packet.params):
        servo = bus.servos.get(sid)
        if servo is not None and servo.get("status_return_level") >= 1:
            error, data = servo.read(address, length)
            bus.reply(servo, servo.error_byte(error), data)


def fast_read(bus: ServoBus, requests: list[tuple[int, int, int]]) -> None:
    """One status packet for all; it stops where a servo is absent or silent."""
    parts: list[tuple[int, int, bytes]] = []
    first: EmulatedServo | None = None
    corrupt: int | None = None  # where the first corrupting servo's CRC lies (later parts fail too)
    for sid, address, length in requests:
        servo = bus.servos.get(sid)
        plan = bus.faults.get(sid)
        if servo is None or servo.get("status_return_level") == 0 or (
                plan is not None and (plan.mute or plan.drop)):
            if plan is not None and plan.drop:
                plan.drop -= 1
                bus.stats["dropped"] += 1
            break
        if plan is not None and plan.corrupt:
            plan.corrupt -= 1
            bus.stats["corrupted"] += 1
            if corrupt is None:
                corrupt = 8 + sum(4 + len(d) for _, _, d in parts) + 2 + length
        error, data = servo.read(address, length)
        if error:
            data = bytes(length)
        parts.append((servo.error_byte(error), sid, data))
        first = first or servo
    if first is None:
        return
    if len(parts) < len(requests):  # the length field still counts every servo
        length_all = 1 + sum(4 + n for _, _, n in requests)
        out = bytearray(pk.fast_read_status(parts))
        out[5:7] = length_all.to_bytes(2, "little")
        data = bytes(out)
    else:
        data = pk.fast_read_status(parts)
    if corrupt is not None:
        data = data[:corrupt] + bytes([data[corrupt] ^ 0xFF]) + data[corrupt + 1:]
    late = sum(bus.faults[sid].late_s for sid, _, _ in requests if sid in bus.faults)
    bus.delay(first, late)
    bus.write_raw(data)


def fast_sync_read(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    if packet.id != pk.BROADCAST_ID or len(packet.params) < 5:
        return
    address, length = _u16(packet.params, 0), _u16(packet.params, 2)
    fast_read(bus, [(sid, address, length) for sid in packet.params[4:]])


def fast_bulk_read(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    fast_read(bus, _bulk_items(packet.params))


def sync_write(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    if packet.id != pk.BROADCAST_ID or len(packet.params) < 5:
        return
    address, length = _u16(packet.params, 0), _u16(packet.params, 2)
    body = packet.params[4:]
    for i in range(0, len(body) - length, length + 1):
        servo = bus.servos.get(body[i])
        if servo is not None:
            servo.write(address, body[i + 1:i + 1 + length], now)


def bulk_write(bus: ServoBus, packet: pk.Packet, now: int) -> None:
    body, i = packet.params, 0
    while i + 5 <= len(body):
        sid, address, length = body[i], _u16(body, i + 1), _u16(body, i + 3)
        servo = bus.servos.get(sid)
        if servo is not None:
            servo.write(address, body[i + 5:i + 5 + length], now)
        i += 5 + length


def _u16(data: bytes, i: int) -> int:
    return data[i] | data[i + 1] << 8


def _bulk_items(params: bytes) -> list[tuple[int, int, int]]:
    return [(params[i], _u16(params, i + 1), _u16(params, i + 3))
            for i in range(0, len(params) - 4, 5)]


READS = {pk.INST_READ, pk.INST_SYNC_READ, pk.INST_FAST_SYNC_READ, pk.INST_BULK_READ,
         pk.INST_FAST_BULK_READ}
"""Instructions before which the servos' motion is brought up to date."""
MOVES = {pk.INST_WRITE, pk.INST_SYNC_WRITE, pk.INST_BULK_WRITE, pk.INST_ACTION,
         pk.INST_REBOOT, pk.INST_FACTORY_RESET, pk.INST_CLEAR}
"""Instructions after which it is (a goal or the torque may have changed)."""


HANDLERS = {
    pk.INST_PING: ping, pk.INST_READ: read,
    pk.INST_WRITE: write_inst, pk.INST_REG_WRITE: reg_write,
    pk.INST_ACTION: action, pk.INST_FACTORY_RESET: factory_reset,
    pk.INST_REBOOT: reboot, pk.INST_CLEAR: clear,
    pk.INST_SYNC_READ: sync_read, pk.INST_SYNC_WRITE: sync_write,
    pk.INST_BULK_READ: bulk_read, pk.INST_BULK_WRITE: bulk_write,
    pk.INST_FAST_SYNC_READ: fast_sync_read,
    pk.INST_FAST_BULK_READ: fast_bulk_read,
}
