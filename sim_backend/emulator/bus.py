"""A Dynamixel Protocol 2.0 bus on a pseudo-terminal: the real SDK opens it like /dev/ttyUSB0.

A background thread reads instruction packets from the pty master, hands them to the
emulated servos and writes their status packets back, honouring Status Return Level,
Return Delay Time and broadcast rules. Faults can be injected per servo (no reply, corrupted
CRC, late reply, hardware error bits). A plant (hardware in the loop) may hold the joints
where the simulated surface stops them. Tests synchronise on `wait_until`, never on sleeps.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from firmware_if import packets as pk
from service.daemon.priority import Scheduling, set_thread_priority
from sim_backend.clock import Clock, MonotonicClock
from sim_backend.emulator.instructions import HANDLERS, MOVES, READS
from sim_backend.emulator.servo import ERR_CRC, ERR_INSTRUCTION, EmulatedServo


@dataclass
class FaultPlan:
    """Faults of one servo. Counts are used up one reply at a time."""

    drop: int = 0
    """Swallow this many of the next replies."""
    corrupt: int = 0
    """Flip the CRC of this many of the next replies."""
    late_s: float = 0.0
    """Delay every reply by this long (past the host's timeout, it is a late reply)."""
    mute: bool = False
    """Never reply (unplugged servo)."""


class Plant(Protocol):
    """Couples servo drives to a physical model (see `sim_backend.emulator.plant`)."""

    def home_ticks(self) -> dict[int, int]:
        """Where the servos power up: {id: Present Position ticks}."""

    def update(self, servos: dict[int, EmulatedServo]) -> None: ...


class ServoBus:
    """The emulated bus. Use as a context manager; `port` is the path to open."""

    def __init__(self, servos: list[EmulatedServo], *, plant: Plant | None = None,
                 clock: Clock | None = None, fast_read: bool = True,
                 honour_return_delay: bool = True, link: str | None = None,
                 priority: int = 0) -> None:
        self.servos = {s.id: s for s in servos}
        self.plant = plant
        self.clock = clock or MonotonicClock()
        self.fast_read = fast_read
        """False emulates firmware before v45: Fast Sync/Bulk Read are not understood."""
        self.honour_return_delay = honour_return_delay
        self.faults: dict[int, FaultPlan] = {}
        self.stats: Counter[str] = Counter()
        self.errors: list[Exception] = []
        """Exceptions raised while handling packets (the packet is dropped, serving goes on)."""
        self.port = ""
        self.link = link
        """A stable path made a symlink to the pty (as udev's /dev/serial/by-id/... names an
        adapter), so a restarted emulator is found where the last one was."""
        self.priority = priority
        """SCHED_FIFO priority of the thread that answers (0: ordinary): servos answer
        whatever the host does, and an emulator starved on a loaded machine answered late
        enough to fault an idle bus (`haptic emulate --priority`)."""
        self.scheduling: Scheduling | None = None
        """What the answering thread got (set once it runs)."""
        self._started = threading.Event()
        self._master = self._slave = -1
        self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self.lock = threading.RLock()
        """Held while packets are processed; hold it to change servos from another thread."""

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> ServoBus:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        if self.link is not None:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            os.symlink(self.port, tmp)
            os.replace(tmp, self.link)  # atomically: a reader never sees no link
            self.port = self.link
        self._wake_r, self._wake_w = os.pipe()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="servo-bus", daemon=True)
        self._started.clear()
        self._thread.start()
        self._started.wait()
        return self

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        self._thread = None
        tty_path = os.ttyname(self._slave)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            os.close(fd)
        self._master = self._slave = self._wake_r = self._wake_w = -1
        if self.link is not None and os.path.islink(self.link) \
                and os.readlink(self.link) == tty_path:
            os.unlink(self.link)  # ours: a successor's link is left alone

    def __enter__(self) -> ServoBus:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- test hooks ----------------------------------------------------------------------
    def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        """Block until `predicate()` holds after some packet was handled (or the timeout)."""
        with self._cond:
            return self._cond.wait_for(predicate, timeout)

    def fault(self, servo_id: int) -> FaultPlan:
        return self.faults.setdefault(servo_id, FaultPlan())

    def inject_hardware_error(self, servo_id: int, bits: int) -> None:
        """Latch Hardware Error Status bits; shutdown bits turn the torque off."""
        with self.lock:
            servo = self.servos[servo_id]
            servo.set("hardware_error_status", bits)
            if bits & servo.get("shutdown"):
                servo.set("torque_enable", 0)
                servo.on_torque_change()

    # -- serving -------------------------------------------------------------------------
    def _serve(self) -> None:
        try:
            if self.priority:
                self.scheduling = set_thread_priority(
                    self.priority, "the emulated servos keep ordinary scheduling and may "
                    "answer late on a loaded machine (a bus fault without a drill)",
                    "pass --priority 0 to stop asking")
        finally:
            self._started.set()  # `start` waits for this
        buf = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master, self._wake_r], [], [])
            if self._wake_r in ready:
                break
            try:
                chunk = os.read(self._master, 4096)
            except OSError:  # the last client closed the port: keep serving
                chunk = b""
            if not chunk:
                # A closed slave makes the master readable forever: wait for writes instead.
                select.select([self._wake_r], [], [], 0.01)
                continue
            buf += chunk
            for packet in self._extract(buf):
                with self.lock:
                    try:
                        self._handle(packet)
                    except Exception as exc:  # an emulator bug must not kill the bus thread
                        self.stats["handler_errors"] += 1
                        self.errors.append(exc)
                with self._cond:
                    self._cond.notify_all()

    def _extract(self, buf: bytearray) -> list[bytes]:
        """Complete packets at the front of `buf` (consumed); garbage before a header dropped.

        An unstuffed header pattern inside a packet body means the sender did not byte-stuff:
        a servo takes it as the start of a new packet, so the partial one is lost.
        """
        out = []
        while True:
            start = buf.find(pk.HEADER)
            if start < 0:
                del buf[:max(0, len(buf) - 3)]
                return out
            del buf[:start]
            if len(buf) < 7:
                return out
            length = buf[5] | buf[6] << 8
            body_end = 7 + length - 2
            inner = buf.find(pk.HEADER[:3], 7)
            while 0 <= inner < body_end and inner + 3 < len(buf) and buf[inner + 3] == 0xFD:
                inner = buf.find(pk.HEADER[:3], inner + 4)
            if 0 <= inner < body_end and inner + 3 < len(buf):
                self.stats["resync"] += 1
                del buf[:inner]
                continue
            if len(buf) < 7 + length:
                return out
            out.append(bytes(buf[:7 + length]))
            del buf[:7 + length]

    def _handle(self, raw: bytes) -> None:
        self.stats["rx_packets"] += 1
        now = self.clock.now_ns()
        try:
            packet = pk.parse(raw)
        except pk.PacketError:
            self.stats["rx_bad"] += 1
            target = self.servos.get(raw[4])
            if target is not None and pk.crc16(raw[:-2]) != (raw[-2] | raw[-1] << 8):
                self.reply(target, target.error_byte(ERR_CRC))
            return
        if packet.instruction in READS:
            self._advance(now)
        handler = HANDLERS.get(packet.instruction)
        if handler is None or (packet.instruction in (pk.INST_FAST_SYNC_READ,
                                                      pk.INST_FAST_BULK_READ)
                               and not self.fast_read):
            self.stats["unknown_instruction"] += 1
            servo = self.servos.get(packet.id)
            if servo is not None:
                self.reply(servo, servo.error_byte(ERR_INSTRUCTION))
            return
        handler(self, packet, now)
        if packet.instruction in MOVES:
            self._advance(now)

    def _advance(self, now: int) -> None:
        for servo in self.servos.values():
            servo.advance(now)
        if self.plant is not None:
            self.plant.update(self.servos)
        tick = (now // 1_000_000) % 32768
        for servo in self.servos.values():
            servo.set("realtime_tick", tick)

    def targets(self, packet_id: int) -> list[EmulatedServo]:
        if packet_id == pk.BROADCAST_ID:
            return [self.servos[k] for k in sorted(self.servos)]
        servo = self.servos.get(packet_id)
        return [servo] if servo is not None else []

    def wants_reply(self, servo: EmulatedServo, packet: pk.Packet, is_read: bool) -> bool:
        level = servo.get("status_return_level")
        if packet.instruction == pk.INST_PING:
            return True
        if packet.id == pk.BROADCAST_ID:
            return False
        return level == 2 or (level == 1 and is_read)

    def delay(self, servo: EmulatedServo, late_s: float | None = None) -> None:
        delay = servo.get("return_delay_time") * 2e-6 if self.honour_return_delay else 0.0
        plan = self.faults.get(servo.id)
        if late_s is not None:
            delay += late_s
        elif plan is not None:
            delay += plan.late_s
        if delay > 0:
            time.sleep(delay)  # the servo's own turnaround time, not a test synchronisation

    def reply(self, servo: EmulatedServo, error: int, params: bytes = b"") -> None:
        self.send(servo, pk.status(servo.id, error, params))

    def send(self, servo: EmulatedServo, data: bytes) -> None:
        plan = self.faults.get(servo.id)
        if plan is not None:
            if plan.mute or plan.drop:
                plan.drop = max(0, plan.drop - 1)
                self.stats["dropped"] += 1
                return
            if plan.corrupt:
                plan.corrupt -= 1
                data = data[:-1] + bytes([data[-1] ^ 0xFF])
                self.stats["corrupted"] += 1
        self.delay(servo)
        self.write_raw(data)

    def write_raw(self, data: bytes) -> None:
        self.stats["tx_packets"] += 1
        view = memoryview(data)
        while view:
            n = os.write(self._master, view)
            view = view[n:]

