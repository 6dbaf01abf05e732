"""Each dynamixel-sdk 4.1.0 defect worked around in `firmware_if.sdk_fixes`: every test shows
the stock SDK failing and the fixed one succeeding, so a fixed upstream release shows up here."""

from __future__ import annotations

import time

import pytest
from dynamixel_sdk.port_handler import PortHandler
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler
from dynamixel_sdk.robotis_def import COMM_SUCCESS

from firmware_if import packets as pk
from firmware_if.sdk_fixes import FixedPacketHandler, PacedPortHandler, PortBusy
from sim_backend.emulator import EmulatedServo, ServoBus

AWKWARD = [0xFF, 0xFF, 0xFD, 0xFF]  # Homing Offset -131073: needs byte stuffing


class CapturePort:
    """Enough of a PortHandler to capture what the packet handler transmits."""

    is_using = False
    sent = b""

    def clearPort(self) -> None:  # noqa: N802
        pass

    def writePort(self, packet: list[int]) -> int:  # noqa: N802
        self.sent = bytes(packet)
        return len(packet)


class PatientPort(PacedPortHandler):
    """Waits up to 0.5 s for a reply, sleeping in select().

    These tests are about the bytes of packets, not timing; the emulator shares this
    process (and its GIL) with the waiting test, so under load the SDK's 34 ms can pass
    before it answers, and a byte test would fail for a scheduling reason.
    """

    PATIENCE_MS = 500.0

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802
        PortHandler.setPacketTimeout(self, packet_length)
        self.packet_timeout = self.PATIENCE_MS

    def setPacketTimeoutMillis(self, msec: float) -> None:  # noqa: N802
        PortHandler.setPacketTimeoutMillis(self, msec)
        self.packet_timeout = max(self.packet_timeout, self.PATIENCE_MS)


@pytest.fixture
def emulator():
    with ServoBus([EmulatedServo(i) for i in (1, 2, 3)], honour_return_delay=False) as bus:
        yield bus


def _open(port: PortHandler, ph: Protocol2PacketHandler) -> PortHandler:
    assert port.openPort()
    return port


# -- 1. transmit stuffing ------------------------------------------------------------------
def test_tx_stuffing_stock_sends_unstuffed_packet():
    port = CapturePort()
    Protocol2PacketHandler().writeTxOnly(port, 1, 20, 4, AWKWARD)
    body = port.sent[7:-2]
    assert pk.has_unstuffed_header(body)  # the defect


def test_tx_stuffing_fixed_sends_a_valid_stuffed_packet():
    port = CapturePort()
    FixedPacketHandler().writeTxOnly(port, 1, 20, 4, AWKWARD)
    parsed = pk.parse(port.sent)
    assert parsed.params == bytes([20, 0] + AWKWARD)
    assert not pk.has_unstuffed_header(port.sent[7:-2])


@pytest.mark.parametrize(("handler", "works"), [(Protocol2PacketHandler, False),
                                                (FixedPacketHandler, True)])
def test_tx_stuffing_on_the_bus(emulator, handler, works):
    port = _open(PatientPort(emulator.port), handler())
    result, error = handler().write4ByteTxRx(port, 2, 20, 0xFFFDFFFF)
    port.closePort()
    assert (result == COMM_SUCCESS) is works
    assert (emulator.servos[2].get("homing_offset") == -131073) is works


# -- 2. receive destuffing -----------------------------------------------------------------
@pytest.mark.parametrize(("handler", "works"), [(Protocol2PacketHandler, False),
                                                (FixedPacketHandler, True)])
def test_rx_destuffing_on_the_bus(emulator, handler, works):
    pattern = bytes([0xFF, 0xFF, 0xFD, 0x00, 0x01, 0xFF, 0xFD, 0xFD, 0x05])
    emulator.servos[1].mem[224:224 + len(pattern)] = pattern  # Indirect Data 1..9
    port = _open(PatientPort(emulator.port), handler())
    data, result, _ = handler().readTxRx(port, 1, 224, len(pattern))
    port.closePort()
    assert result == COMM_SUCCESS
    assert (bytes(data) == pattern) is works


# -- 3. fast bulk read decoding --------------------------------------------------------------
@pytest.mark.parametrize(("handler", "works"), [(Protocol2PacketHandler, False),
                                                (FixedPacketHandler, True)])
def test_fast_bulk_read_decoding(emulator, handler, works):
    emulator.servos[1].set("present_current", 77)
    emulator.servos[2].set("present_position", 3000)
    emulator.servos[3].set("present_current", -5)
    # id 2 equals servo 1's length byte: param.index(2) finds the wrong record
    param = [1, 126, 0, 2, 0, 2, 132, 0, 4, 0, 3, 126, 0, 2, 0]
    ph = handler()
    port = _open(PatientPort(emulator.port), ph)
    assert ph.bulkReadTx(port, param, len(param), True) == COMM_SUCCESS
    decoded, result = ph.fastBulkReadRx(port, param)
    port.closePort()
    assert result == COMM_SUCCESS
    expected = {1: list((77).to_bytes(2, "little")), 2: list((3000).to_bytes(4, "little")),
                3: list((-5).to_bytes(2, "little", signed=True))}
    assert ({k: list(v) for k, v in decoded.items()} == expected) is works


# -- 4. busy polling and unbounded timeouts --------------------------------------------------
def _counting(port_cls: type[PortHandler]) -> type[PortHandler]:
    class Counting(port_cls):  # type: ignore[valid-type, misc]
        reads = 0

        def readPort(self, length: int):  # noqa: N802
            self.reads += 1
            return super().readPort(length)

    return Counting


@pytest.mark.parametrize(("port_cls", "spins"), [(PortHandler, True), (PacedPortHandler, False)])
def test_waiting_for_a_silent_servo(emulator, port_cls, spins):
    emulator.fault(3).mute = True
    port = _open(_counting(port_cls)(emulator.port), FixedPacketHandler())
    wall = time.perf_counter()
    _, result, _ = FixedPacketHandler().read4ByteTxRx(port, 3, 132)
    wall = time.perf_counter() - wall
    port.closePort()
    assert result != COMM_SUCCESS
    assert wall >= 0.02  # both wait out the timeout...
    assert (port.reads > 100) is spins  # ...but the stock port polls the serial port in a loop
    assert spins or port.reads <= 5


def test_paced_port_bounds_the_timeout_by_its_budget(emulator):
    emulator.fault(3).mute = True
    port = _open(PacedPortHandler(emulator.port, budget_ms=3.0), FixedPacketHandler())
    wall = time.perf_counter()
    _, result, _ = FixedPacketHandler().read4ByteTxRx(port, 3, 132)
    wall = time.perf_counter() - wall
    port.closePort()
    assert result != COMM_SUCCESS
    assert wall < 0.025  # the stock allowance is 34 ms


# -- 5. an exclusive port ------------------------------------------------------------------
@pytest.mark.parametrize(("port_cls", "shared"), [(PortHandler, True), (PacedPortHandler, False)])
def test_a_second_process_cannot_open_a_port_in_use(emulator, port_cls, shared):
    """Two daemons on one bus took each other's replies and both faulted (a held-out fault
    check): the stock port opens a port in use; the fixed one refuses it, naming why."""
    first = _open(port_cls(emulator.port), Protocol2PacketHandler())
    try:
        second = port_cls(emulator.port)
        if shared:
            assert second.openPort()
            second.closePort()
        else:
            with pytest.raises(PortBusy, match="another process has .* open"):
                second.openPort()
    finally:
        first.closePort()
    again = port_cls(emulator.port)
    assert again.openPort()  # free again once the first closes
    again.closePort()


# -- 6. a late reply taken as the next exchange's answer -------------------------------------
@pytest.mark.parametrize(("handler", "works"), [(Protocol2PacketHandler, False),
                                                (FixedPacketHandler, True)])
def test_a_late_ping_answer_is_not_a_read_s_answer(emulator, handler, works):
    """A ping given up on answers during the next read of the same servo: the stock SDK
    takes model 1020's low byte (0xFC) as Hardware Error Status."""
    ph = handler()
    port = _open(PacedPortHandler(emulator.port), ph)
    emulator.fault(1).late_s = 0.05  # past the ping's 34 ms, inside the read's window
    assert ph.ping(port, 1)[1] != COMM_SUCCESS
    emulator.fault(1).late_s = 0.0
    data, result, _ = ph.readTxRx(port, 1, 70, 1)  # Hardware Error Status
    port.closePort()
    assert result == COMM_SUCCESS
    assert (data == [0]) is works, data
