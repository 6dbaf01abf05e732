"""Every workaround for dynamixel-sdk 4.1.0 defects, in one place.

Each defect has a test in tests/firmware_if/test_sdk_fixes.py that fails on the stock SDK:

1. Transmit byte stuffing is lost. `Protocol2PacketHandler.txPacket` calls `addStuffing`
   and ignores its result; when stuffing is needed `addStuffing` builds a new list, so the
   packet goes out unstuffed with the unstuffed length. A servo sees the header pattern
   0xFF 0xFF 0xFD inside the body and drops the packet. Fix: stuff in place.
2. Receive byte stuffing is removed wrongly. `removeStuffing` compacts the packet in place
   while testing the bytes it has already overwritten, so after one stuffed sequence any
   later "xx 0xFF 0xFD 0xFD" loses a byte. Fix: destuff from an untouched copy.
3. Fast Bulk Read is decoded with `param.index(dxl_id)`, which finds the first *byte* equal
   to the id anywhere in the request (an address or a length byte), so data lengths and ids
   are mismatched. Both fast decoders also drop every servo's error byte (the hardware
   alert). Fix: walk the request in 5-byte records; `packets.split_fast_read` keeps error bytes.
4. The port busy-polls with `timeout=0` reads and times packets with the wall clock
   (`time.time`), with a fixed 2 x 16 ms latency allowance. Fix: `PacedPortHandler` waits
   in `select()` for bytes until a monotonic deadline bounded by the caller's budget.
5. `setupPort` opens the port without a lock, so two processes (a second hapticd, a
   `haptic bus` beside a running daemon) can share one bus: each takes the other's replies
   and both fault on "Incorrect status packet". Fix: open it with pyserial's `exclusive`
   lock, so the second open fails at once (`PortBusy`).
6. A reply is whatever status comes next from the id asked. `txRxPacket` and `readRx` take
   the first status packet with that id, whatever it answers, and `clearPort` drops only
   what has already arrived, so a reply given up on (a late servo) lands in the next
   exchange: a ping's late answer (model 1020, low byte 0xFC) was read as Hardware Error
   Status ("overheating, encoder, shock, overload") and a healthy servo was rebooted. Fix: an
   answer must come from the id asked and have the shape of the answer to what was asked
   (`answers`); anything else is skipped, and after an exchange that missed its answer or met
   a stray one, the next that expects a reply first lets the line fall quiet (`settle`;
   outside the control cycle, which cannot wait: `settles`).
"""

from __future__ import annotations

import select
import termios
import time

import serial
from dynamixel_sdk.port_handler import PortHandler
from dynamixel_sdk.protocol2_packet_handler import (
    PKT_ERROR,
    PKT_ID,
    PKT_INSTRUCTION,
    PKT_LENGTH_H,
    PKT_LENGTH_L,
    PKT_PARAMETER0,
    Protocol2PacketHandler,
)
from dynamixel_sdk.robotis_def import (
    BROADCAST_ID,
    COMM_RX_CORRUPT,
    COMM_SUCCESS,
    INST_ACTION,
    INST_BULK_READ,
    INST_PING,
    INST_READ,
    INST_SYNC_READ,
)

from firmware_if import packets

SETUP_TIMEOUT_MS = 34.0
"""Packet timeout outside the control cycle (setup, scan, single reads): the SDK's own."""
RX_TIMEOUT_RESULTS = (-3001,)  # COMM_RX_TIMEOUT
"""The SDK's result for a reply that did not come in time."""
PORT_ERRORS = (OSError, termios.error)
"""What a failing serial port raises (pyserial's SerialException is an OSError)."""

SETTLE_CAP = 8
"""A settle stops after this many quiet windows even while bytes still come (a babbling
line): it bounds the wait; the answer's id and shape still keep a stray out."""
_REPLIES_WHEN_BROADCAST = (INST_PING, INST_SYNC_READ, INST_BULK_READ, packets.INST_FAST_SYNC_READ,
                           packets.INST_FAST_BULK_READ)


def wants_reply(txpacket: list[int]) -> bool:
    """Whether a servo answers this instruction packet (status return level 2)."""
    if txpacket[PKT_INSTRUCTION] in _REPLIES_WHEN_BROADCAST:
        return True
    return txpacket[PKT_ID] != BROADCAST_ID and txpacket[PKT_INSTRUCTION] != INST_ACTION


PING_ANSWER_LENGTH = 3
"""Parameters of a ping's answer: the model number (2 bytes) and the firmware version."""


def answer_length(txpacket: list[int]) -> int:
    """Parameters of the status that answers a single-servo instruction packet: a ping's
    model and firmware, a read's data, nothing for a write, reboot or clear."""
    if txpacket[PKT_INSTRUCTION] == INST_PING:
        return PING_ANSWER_LENGTH
    if txpacket[PKT_INSTRUCTION] == INST_READ:
        return txpacket[PKT_PARAMETER0 + 2] | txpacket[PKT_PARAMETER0 + 3] << 8
    return 0


def answers(rxpacket: list[int], servo_id: int, length: int) -> bool:
    """Whether a (destuffed) status packet is `servo_id`'s answer with `length` parameters;
    a status with an error and no parameters answers anything (a servo refusing)."""
    params = (rxpacket[PKT_LENGTH_L] | rxpacket[PKT_LENGTH_H] << 8) - 4
    return rxpacket[PKT_ID] == servo_id and (
        params == length or (params == 0 and bool(rxpacket[PKT_ERROR] & 0x7F)))


class FixedPacketHandler(Protocol2PacketHandler):
    """Protocol 2.0 packet handler with defects 1-3 and 6 fixed."""

    def txPacket(self, port: PortHandler, txpacket: list[int]) -> int:  # noqa: N802
        if isinstance(port, PacedPortHandler) and port.unsettled and port.settles \
                and wants_reply(txpacket):
            port.settle()  # a write no servo answers (torque off) goes at once
        return super().txPacket(port, txpacket)

    def txRxPacket(self, port: PortHandler, txpacket: list[int]  # noqa: N802
                   ) -> tuple[list[int] | None, int, int]:
        servo_id, length = txpacket[PKT_ID], answer_length(txpacket)
        if servo_id == BROADCAST_ID or txpacket[PKT_INSTRUCTION] in (
                INST_ACTION, INST_SYNC_READ, INST_BULK_READ):
            return super().txRxPacket(port, txpacket)  # no single answer to check
        result = self.txPacket(port, txpacket)
        if result != COMM_SUCCESS:
            return None, result, 0
        port.setPacketTimeout(length + 11)  # as the SDK: a status of that many parameters
        rxpacket = self._answer(port, servo_id, length)
        if isinstance(rxpacket, int):
            return None, rxpacket, 0
        return rxpacket, COMM_SUCCESS, rxpacket[PKT_ERROR]

    def readRx(self, port: PortHandler, dxl_id: int, length: int  # noqa: N802
               ) -> tuple[list[int], int, int]:
        rxpacket = self._answer(port, dxl_id, length)
        if isinstance(rxpacket, int):
            return [], rxpacket, 0
        data = rxpacket[PKT_PARAMETER0 + 1:PKT_PARAMETER0 + 1 + length]
        return data, COMM_SUCCESS, rxpacket[PKT_ERROR]

    def _answer(self, port: PortHandler, servo_id: int, length: int) -> list[int] | int:
        """The first status that `answers` (skipping strays until the packet timeout), or the
        result code of the failure."""
        while True:
            rxpacket, result = self.rxPacket(port, False)
            if result != COMM_SUCCESS:
                return result
            if answers(rxpacket, servo_id, length):
                return rxpacket
            if isinstance(port, PacedPortHandler):
                port.unsettled = True  # a backlog of late replies: let it pass first

    def addStuffing(self, packet: list[int]) -> list[int]:  # noqa: N802 (SDK name)
        stuffed = super().addStuffing(list(packet))
        packet[:] = stuffed  # the SDK's caller keeps using its own list: change it in place
        return packet

    def removeStuffing(self, packet: list[int]) -> list[int]:  # noqa: N802
        length = packet[5] | packet[6] << 8
        body = packets.unstuff(bytes(packet[7:7 + length - 2]))
        crc = packet[7 + length - 2:7 + length]
        packet[7:] = list(body) + list(crc)
        new_length = len(body) + 2
        packet[5], packet[6] = new_length & 0xFF, new_length >> 8
        return packet

    def fastBulkReadRx(self, port: PortHandler, param: list[int]  # noqa: N802
                       ) -> tuple[dict[int, list[int]], int]:
        rxpacket, result = self.rxPacket(port, True)
        if result != COMM_SUCCESS:
            return {}, result
        lengths = [(param[i], param[i + 3] | param[i + 4] << 8)
                   for i in range(0, len(param) - 4, 5)]
        try:
            decoded = packets.split_fast_read(bytes(rxpacket), lengths)
        except packets.PacketError:
            return {}, COMM_RX_CORRUPT
        return {sid: list(data) for sid, (_, data) in decoded.items()}, COMM_SUCCESS


class PortBusy(serial.SerialException):
    """Another process holds the port's lock."""


class PacedPortHandler(PortHandler):
    """A PortHandler that sleeps in select() instead of spinning, on a monotonic clock.

    `budget_ms` caps every packet timeout: the SDK's own allowance (2 x 16 ms latency
    timer + 2 ms) would let one silent servo eat several control cycles.
    """

    def __init__(self, port_name: str, budget_ms: float = 34.0) -> None:
        super().__init__(port_name)
        self.budget_ms = budget_ms
        self.unsettled = False
        """An answer was missed or a stray status met: replies may still be coming."""
        self.settles = True
        """Whether an exchange after a miss settles first. The control cycle clears it: it
        cannot wait for a late reply, and a settle only moved a late Fast Sync Read's reply
        (the shape of the next one's answer) into the next cycle's window: a late servo's
        cycles failed every other time and never latched a fault."""

    def setupPort(self, cflag_baud: int) -> bool:  # noqa: N802
        if self.is_open:
            self.closePort()
        try:
            self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate,
                                     bytesize=serial.EIGHTBITS, timeout=0, exclusive=True)
        except serial.SerialException as exc:
            if "exclusively lock" in str(exc):  # pyserial's words for a flock that failed
                raise PortBusy(f"another process has {self.port_name} open (a second "
                               f"hapticd, or haptic bus beside a running daemon?); stop it "
                               f"or use another port") from None
            raise
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def getCurrentTime(self) -> float:  # noqa: N802
        return time.monotonic_ns() / 1e6

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802
        super().setPacketTimeout(packet_length)
        transfer = self.tx_time_per_byte * packet_length
        self.packet_timeout = min(self.packet_timeout, transfer + self.budget_ms)

    def isPacketTimeout(self) -> bool:  # noqa: N802
        if super().isPacketTimeout():
            self.unsettled = True  # the answer given up on may yet come
            return True
        return False

    def settle(self, quiet_ms: float | None = None, cap_ms: float | None = None) -> None:
        """Read and drop what arrives until no byte has come for `quiet_ms` (the packet
        budget: as long as an answer is waited for), at most `cap_ms` (`SETTLE_CAP` quiet
        windows): late replies to exchanges given up on, which would land in the next."""
        quiet = self.budget_ms if quiet_ms is None else quiet_ms
        end = self.getCurrentTime() + (SETTLE_CAP * quiet if cap_ms is None else cap_ms)
        while (left := end - self.getCurrentTime()) > 0:
            wait = min(quiet, left)
            if not select.select([self.ser.fileno()], [], [], wait / 1e3)[0]:
                self.unsettled = wait < quiet  # cut by the cap: not known to be quiet
                return
            self.ser.read(max(self.ser.in_waiting, 1))

    def readPort(self, length: int) -> bytes:  # noqa: N802
        if self.ser.in_waiting == 0 and length > 0:
            remaining_ms = self.packet_timeout - (self.getCurrentTime() - self.packet_start_time)
            if remaining_ms > 0:
                select.select([self.ser.fileno()], [], [], remaining_ms / 1e3)
        return self.ser.read(min(length, self.ser.in_waiting) if length > 0 else 0)
