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
"""

from __future__ import annotations

import select
import time

import serial
from dynamixel_sdk.port_handler import PortHandler
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler
from dynamixel_sdk.robotis_def import COMM_RX_CORRUPT, COMM_SUCCESS

from firmware_if import packets


class FixedPacketHandler(Protocol2PacketHandler):
    """Protocol 2.0 packet handler with defects 1-3 fixed."""

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

    def readPort(self, length: int) -> bytes:  # noqa: N802
        if self.ser.in_waiting == 0 and length > 0:
            remaining_ms = self.packet_timeout - (self.getCurrentTime() - self.packet_start_time)
            if remaining_ms > 0:
                select.select([self.ser.fileno()], [], [], remaining_ms / 1e3)
        return self.ser.read(min(length, self.ser.in_waiting) if length > 0 else 0)
