"""Protocol 2.0 packets as pure functions: CRC-16, byte stuffing, building and parsing.

Written from the e-Manual (Protocol 2.0, "Packet Process") rather than taken from the SDK,
so that the emulator and the SDK workarounds are checked against an independent reading.
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
INST_PING, INST_READ, INST_WRITE, INST_REG_WRITE, INST_ACTION = 0x01, 0x02, 0x03, 0x04, 0x05
INST_FACTORY_RESET, INST_REBOOT, INST_CLEAR, INST_STATUS = 0x06, 0x08, 0x10, 0x55
INST_SYNC_READ, INST_SYNC_WRITE, INST_FAST_SYNC_READ = 0x82, 0x83, 0x8A
INST_BULK_READ, INST_BULK_WRITE, INST_FAST_BULK_READ = 0x92, 0x93, 0x9A


def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 (polynomial 0x8005, no reflection) over `data`, continuing from `crc`."""
    for byte in data:
        crc = ((crc << 8) ^ _TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert 0xFD after every 0xFF 0xFF 0xFD in instruction..parameters (not the CRC)."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the 0xFD added after every 0xFF 0xFF 0xFD (the inverse of `stuff`)."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and len(out) >= 3 and out[-3:-1] == b"\xff\xff" \
                and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # skip the stuffed byte
        i += 1
    return bytes(out)


def has_unstuffed_header(body: bytes) -> bool:
    """True when the body holds 0xFF 0xFF 0xFD not followed by the stuffing 0xFD."""
    i = 0
    while i + 2 < len(body):
        if body[i:i + 3] == b"\xff\xff\xfd":
            if i + 3 >= len(body) or body[i + 3] != 0xFD:
                return True
            i += 4
            continue
        i += 1
    return False


def packet(packet_id: int, instruction: int, params: bytes = b"", *, stuffing: bool = True
           ) -> bytes:
    """A whole packet: header, id, length, instruction, (stuffed) parameters, CRC."""
    body = bytes([instruction]) + bytes(params)
    if stuffing:
        body = stuff(body)
    length = len(body) + 2
    head = HEADER + bytes([packet_id, length & 0xFF, length >> 8])
    crc = crc16(head + body)
    return head + body + bytes([crc & 0xFF, crc >> 8])


def status(packet_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet (instruction 0x55) as a servo sends it."""
    return packet(packet_id, INST_STATUS, bytes([error]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A received packet, CRC checked and unstuffed."""

    id: int
    instruction: int
    params: bytes
    raw: bytes


class PacketError(ValueError):
    """A packet that is not well formed (reason in the message)."""


def parse(raw: bytes, *, stuffed: bool = True) -> Packet:
    """Check and decode one complete packet (`stuffed=False` for Fast Read status packets)."""
    if len(raw) < 10 or raw[:4] != HEADER:
        raise PacketError("no header")
    length = raw[5] | raw[6] << 8
    if len(raw) != 7 + length:
        raise PacketError(f"length field {length} does not match {len(raw) - 7} bytes")
    crc = raw[-2] | raw[-1] << 8
    if crc16(raw[:-2]) != crc:
        raise PacketError("CRC mismatch")
    body = raw[7:-2]
    if stuffed:
        body = unstuff(body)
    return Packet(raw[4], body[0], bytes(body[1:]), bytes(raw))


def fast_read_status(parts: list[tuple[int, int, bytes]]) -> bytes:
    """One Fast Sync/Bulk Read status packet from (error, id, data) of each servo in order.

    Per the e-Manual: ID 0xFE, no byte stuffing; each servo appends error, id, data and the
    CRC of the packet so far; the last servo's CRC is the packet's.
    """
    length = 1 + sum(4 + len(data) for _, _, data in parts)
    out = bytearray(HEADER + bytes([BROADCAST_ID, length & 0xFF, length >> 8, INST_STATUS]))
    for error, sid, data in parts:
        out += bytes([error, sid]) + data
        crc = crc16(out)
        out += bytes([crc & 0xFF, crc >> 8])
    return bytes(out)


def split_fast_read(raw: bytes, lengths: list[tuple[int, int]]) -> dict[int, tuple[int, bytes]]:
    """Decode a Fast Sync/Bulk Read status: [(id, data length)] in request order ->
    {id: (error, data)}. Raises PacketError on a bad CRC, length or an unexpected id."""
    if len(raw) < 11 or raw[:4] != HEADER or raw[4] != BROADCAST_ID or raw[7] != INST_STATUS:
        raise PacketError("not a fast read status packet")
    length = raw[5] | raw[6] << 8
    expected = 1 + sum(4 + n for _, n in lengths)
    if length != expected or len(raw) != 7 + length:
        raise PacketError(f"fast read length {length}, expected {expected}")
    if crc16(raw[:-2]) != (raw[-2] | raw[-1] << 8):
        raise PacketError(f"CRC mismatch from servo {first_damaged(raw, lengths)}'s part on")
    out: dict[int, tuple[int, bytes]] = {}
    i = 8
    for sid, n in lengths:
        error, got = raw[i], raw[i + 1]
        if got != sid:
            raise PacketError(f"fast read: expected id {sid} at byte {i + 1}, got {got}")
        out[sid] = (error, bytes(raw[i + 2:i + 2 + n]))
        i += 4 + n
    return out


def first_damaged(raw: bytes, lengths: list[tuple[int, int]]) -> int | None:
    """The id of the first servo whose part of a Fast Sync/Bulk Read status fails its CRC,
    [(id, data length)] in request order: each servo's CRC covers the packet so far, so
    damage fails the part it falls in and every part after it (damage in the header fails
    the first). None where the packet's length is not the request's, or every part checks."""
    if len(raw) != 8 + sum(4 + n for _, n in lengths):
        return None
    crc, start, end = 0, 0, 8
    for sid, n in lengths:
        end += 2 + n
        crc = crc16(raw[start:end], crc)  # carried on from the part before
        if crc != (raw[end] | raw[end + 1] << 8):
            return sid
        crc = crc16(raw[end:end + 2], crc)
        start = end = end + 2
    return None
