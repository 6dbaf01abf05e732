"""Packet codec against the e-Manual's examples, and stuffing as an exact inverse."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_if import packets as pk


def h(text: str) -> bytes:
    return bytes.fromhex(text)


@pytest.mark.parametrize(("packet_id", "inst", "params", "expected"), [
    (1, pk.INST_PING, "", "FF FF FD 00 01 03 00 01 19 4E"),
    (0xFE, pk.INST_PING, "", "FF FF FD 00 FE 03 00 01 31 42"),
    (1, pk.INST_READ, "84 00 04 00", "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"),
    (1, pk.INST_WRITE, "74 00 00 02 00 00", "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"),
    (1, pk.INST_REBOOT, "", "FF FF FD 00 01 03 00 08 2F 4E"),
    (1, pk.INST_CLEAR, "01 44 58 4C 22", "FF FF FD 00 01 08 00 10 01 44 58 4C 22 B1 DC"),
    (0xFE, pk.INST_SYNC_READ, "84 00 04 00 01 02",
     "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"),
    (0xFE, pk.INST_SYNC_WRITE, "74 00 04 00 01 96 00 00 00 02 AA 00 00 00",
     "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"),
    (0xFE, pk.INST_BULK_READ, "01 90 00 02 00 02 92 00 01 00",
     "FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05"),
    (0xFE, pk.INST_FAST_SYNC_READ, "84 00 04 00 03 07 04",
     "FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2"),
])
def test_instruction_packets_match_the_e_manual(packet_id, inst, params, expected):
    assert pk.packet(packet_id, inst, h(params)) == h(expected)


def test_status_packets_match_the_e_manual():
    assert pk.status(1, 0, h("06 04 26")) == h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")
    assert pk.status(2, 0, h("24")) == h("FF FF FD 00 02 05 00 55 00 24 8B A9")


def test_fast_sync_read_status_matches_the_e_manual_and_decodes():
    raw = pk.fast_read_status([(0, 3, h("A6 00 00 00")), (0, 7, h("1F 08 00 00")),
                               (0, 4, h("FF 03 00 00"))])
    assert raw == h("FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08"
                    "00 07 1F 08 00 00 16 CA 00 04 FF 03 00 00 D1 9E")
    decoded = pk.split_fast_read(raw, [(3, 4), (7, 4), (4, 4)])
    assert decoded == {3: (0, h("A6 00 00 00")), 7: (0, h("1F 08 00 00")),
                       4: (0, h("FF 03 00 00"))}
    with pytest.raises(pk.PacketError):
        pk.split_fast_read(raw, [(3, 4), (4, 4), (7, 4)])
    with pytest.raises(pk.PacketError):
        pk.split_fast_read(raw[:-1] + b"\x00", [(3, 4), (7, 4), (4, 4)])


def test_a_damaged_fast_read_status_names_the_first_part_that_fails():
    lengths = [(3, 4), (7, 4), (4, 4)]
    raw = pk.fast_read_status([(0, 3, h("A6 00 00 00")), (0, 7, h("1F 08 00 00")),
                               (0, 4, h("FF 03 00 00"))])
    assert pk.first_damaged(raw, lengths) is None
    for at, servo in ((2, 3), (10, 3), (17, 7), (21, 7), (28, 4), (len(raw) - 1, 4)):
        spoiled = raw[:at] + bytes([raw[at] ^ 0x10]) + raw[at + 1:]
        assert pk.first_damaged(spoiled, lengths) == servo, at
    assert pk.first_damaged(raw[:-1], lengths) is None  # short: nothing to say
    with pytest.raises(pk.PacketError, match="from servo 7's part on"):
        pk.split_fast_read(raw[:20] + b"\x01" + raw[21:], lengths)


def test_stuffing_follows_the_rule():
    assert pk.stuff(h("03 FF FF FD 01")) == h("03 FF FF FD FD 01")
    assert pk.stuff(h("FF FF FD FD")) == h("FF FF FD FD FD")
    assert pk.has_unstuffed_header(h("03 FF FF FD 01"))
    assert not pk.has_unstuffed_header(h("03 FF FF FD FD 01"))


@given(st.binary(max_size=64))
def test_unstuff_inverts_stuff_and_leaves_no_header(body):
    stuffed = pk.stuff(body)
    assert pk.unstuff(stuffed) == body
    assert not pk.has_unstuffed_header(stuffed)


@given(st.binary(max_size=40))
def test_parse_inverts_packet(params):
    parsed = pk.parse(pk.packet(7, pk.INST_WRITE, params))
    assert (parsed.id, parsed.instruction, parsed.params) == (7, pk.INST_WRITE, params)


def test_parse_rejects_bad_crc_and_length():
    raw = bytearray(pk.packet(1, pk.INST_PING))
    raw[-1] ^= 1
    with pytest.raises(pk.PacketError, match="CRC"):
        pk.parse(bytes(raw))
    with pytest.raises(pk.PacketError, match="length"):
        pk.parse(pk.packet(1, pk.INST_READ, bytes(4))[:-1])
