"""The Dynamixel bus driver: dynamixel-sdk (Protocol 2.0) with the fixes of `sdk_fixes`.

One control cycle is one Sync Read (Fast Sync Read where every servo supports it, falling
back to Sync Read) of Present Current, Velocity and Position and each servo's clock, plus one
Sync Write of goal positions. Packet timeouts are bounded by the cycle budget; waiting sleeps
in select(). A reply the servo made before the cycle asked (a late answer to an earlier
cycle, `reply_age`) fails the cycle as a timeout does. Consecutive failed cycles are
tolerated up to `failure_tolerance`, then the bus latches a fault and turns torque off;
`reset()` recovers it.

Every SDK call goes through `_sdk`: an error of the port itself (OSError with EIO when the
adapter is unplugged or the emulator stops, termios.error from tcflush, SerialException)
latches a `PortLost` fault at once; any other exception the SDK raises on a bad packet is a
failed cycle like a timeout. Nothing from the serial layer escapes as anything but a
FirmwareError, and `reopen()` gives the bus a fresh port (the same path, or a new one).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from dynamixel_sdk.group_sync_write import GroupSyncWrite
from dynamixel_sdk.robotis_def import (
    BROADCAST_ID,
    COMM_PORT_BUSY,
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    COMM_TX_FAIL,
)

from firmware_if.bus_diagnosis import why_cycles_failed
from firmware_if.errors import (
    BusTimeoutError,
    CommunicationError,
    FirmwareError,
    HardwareFault,
    NotReadyError,
    PortLost,
    StaleReplyError,
)
from firmware_if.packets import PacketError, first_damaged, split_fast_read
from firmware_if.registers import (
    ALERT_BIT,
    REG,
    SYNC_READ_LENGTH,
    SYNC_READ_START,
    describe_hardware_error,
    describe_status_error,
)
from firmware_if.reply_age import STALE_MS, ReplyAges
from firmware_if.sdk_fixes import (
    PORT_ERRORS,
    RX_TIMEOUT_RESULTS,
    SETUP_TIMEOUT_MS,
    FixedPacketHandler,
    PacedPortHandler,
    PortBusy,
)

FAST_READ_MIN_FIRMWARE = 45
SETUP_ATTEMPTS = 3
"""Tries of a single read or write outside the control cycle before its timeout counts: a
reply can miss its window on a loaded host or a noisy line (make test under load: a
configure's read-back failed), and reading or writing a register again is harmless."""
TORQUE_CHECK_CYCLES = 20
"""Control cycles between reads of every servo's Torque Enable while torque should be on: a
servo that restarts (a brown-out) answers as before, with its torque off and its RAM at
defaults, and only this read tells (a fifth of a second at 100 Hz)."""


def _cannot_open(port_name: str, why: object) -> str:
    return (f"cannot open {port_name}: {why}; is the adapter plugged in (or the emulator "
            "running)?")


def check_port_exists(port_name: str) -> None:
    """Refuse a device path that does not exist (`PortLost`), so a command can say so before
    it prints anything; opening the port is still what decides (a URL or a COM name is left
    to `DxlBus.open`)."""
    if port_name.startswith("/") and not os.path.exists(port_name):
        raise PortLost(_cannot_open(port_name, "no such device"))


T = TypeVar("T")


RESULT_WORDS = {
    COMM_RX_TIMEOUT: "no reply in time",
    COMM_RX_CORRUPT: "a garbled reply: noise on the bus, another baud rate, or two servos on "
                     "one id",
    COMM_TX_FAIL: "the port did not take the packet",
    COMM_PORT_BUSY: "the port was busy",
}
"""Plain words for the SDK's communication results, its own ("[TxRxResult] Incorrect status
packet!") after them: a fault's first reason was the SDK's words alone until the diagnosis
after it named the cause."""


def _result_words(handler: Any, result: int) -> str:
    said = handler.getTxRxResult(result)
    return f"{RESULT_WORDS[result]} (the SDK: {said})" if result in RESULT_WORDS else said


@dataclass(frozen=True)
class ServoReading:
    """Raw values of one servo from one cycle."""

    position: int
    velocity: int
    current: int
    error: int
    """Error byte of its status (bit 7: hardware alert)."""
    tick: int = 0
    """Its Realtime Tick when it answered (ms, wrapping at 32768)."""


@dataclass
class BusStats:
    cycles: int = 0
    failures: int = 0
    consecutive_failures: int = 0
    fast_read: bool = False
    last_cycle_ns: int = 0


class DxlBus:
    """A servo bus on one serial port. No I/O before `open()`; use from one thread (a
    fault's diagnosis may run on one of its own: `diagnose_in_background`)."""

    def __init__(self, port: str, ids: Sequence[int], *, baud: int = 1_000_000,
                 cycle_budget_s: float = 0.01, failure_tolerance: int = 3,
                 use_fast_read: bool = True) -> None:
        if not ids:
            raise ValueError("a bus needs at least one servo id")
        self.port_name = port
        self.ids = tuple(ids)
        self.baud = baud
        self.cycle_budget_s = cycle_budget_s
        self.failure_tolerance = failure_tolerance
        self.use_fast_read = use_fast_read
        self.stats = BusStats()
        self.fault: str | None = None
        self.torque_on = False
        """Torque was last switched on (and no fault has switched it off since)."""
        self._port: PacedPortHandler | None = None
        self._ph = FixedPacketHandler()
        self._ages = ReplyAges()
        """Each servo's clock against ours: dates replies (`_fresh`)."""
        self._asked_ns = self._received_ns = 0
        """When the latest sync read began to go out, and when its replies were in
        (monotonic)."""
        self.diagnose_in_background = False
        """Whether the words a fault gets from asking each servo (`why_cycles_failed`, up
        to a second of pings) are found on a thread of their own, so the caller's loop
        keeps its rate: a held-out client saw a daemon's state and replies stop for 0.7-1 s
        when the servos fell silent. Meanwhile the bus is that thread's: other I/O waits
        for it (`_require`), but a best-effort torque off, which the latch has sent, does
        not. `diagnosed` then holds the fault's message before and after."""
        self._diagnosis: threading.Thread | None = None
        self.diagnosed: tuple[str, str] | None = None
        """(the message the latch raised, the same with the diagnosis's words) once a
        background diagnosis has ended, until `take_diagnosis`."""

    # -- lifecycle -----------------------------------------------------------------------
    def open(self) -> None:
        port = PacedPortHandler(self.port_name, budget_ms=SETUP_TIMEOUT_MS)
        try:
            if not port.openPort() or not port.setBaudRate(self.baud):
                raise CommunicationError(f"cannot open {self.port_name} at {self.baud} baud")
        except PortBusy as exc:
            raise PortLost(f"cannot open {self.port_name}: {exc}") from None
        except (*PORT_ERRORS, ValueError) as exc:
            raise PortLost(_cannot_open(self.port_name, exc)) from None
        self._port = port
        self.stats = BusStats()
        self.fault = None
        self._ages.forget()

    def close(self) -> None:
        """Torque off (best effort) and release the port. Safe to call twice."""
        self.wait_for_diagnosis()
        if self._port is None:
            return
        try:
            self.torque(False, best_effort=True)
        finally:
            with contextlib.suppress(*PORT_ERRORS, ValueError):  # the port may be gone
                self._port.closePort()
            self._port = None

    def reopen(self, port: str | None = None) -> None:
        """Release the port (whatever state it is in) and open it again, or `port` instead:
        how a bus recovers from a lost adapter or a restarted emulator."""
        self.wait_for_diagnosis()
        if self._port is not None:
            with contextlib.suppress(*PORT_ERRORS, ValueError):
                self._port.closePort()
            self._port = None
        if port is not None:
            self.port_name = port
        self.open()

    def __enter__(self) -> DxlBus:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._port is not None

    @property
    def diagnosing(self) -> bool:
        """A fault's diagnosis is asking the servos on its own thread."""
        return self._diagnosis is not None and self._diagnosis.is_alive()

    def take_diagnosis(self) -> tuple[str, str] | None:
        """`diagnosed`, once: (the fault's message as latched, with the diagnosis's words)."""
        told, self.diagnosed = self.diagnosed, None
        return told

    def wait_for_diagnosis(self) -> None:
        """Let a background diagnosis end before other I/O (not from its own thread)."""
        diagnosis = self._diagnosis
        if diagnosis is not None and diagnosis is not threading.current_thread():
            diagnosis.join()
            self._diagnosis = None

    def _require(self) -> PacedPortHandler:
        self.wait_for_diagnosis()
        if self._port is None:
            raise NotReadyError(f"bus on {self.port_name} is not open: call open() first")
        return self._port

    def _sdk(self, what: str, call: Callable[..., T], *args: Any) -> T:
        """One SDK call: a port error latches PortLost, any other exception the SDK raises
        is a CommunicationError (a failed exchange), never a crash."""
        port = self._require()
        try:
            return call(*args)
        except FirmwareError:
            raise
        except PORT_ERRORS as exc:
            port.is_using = False  # the SDK leaves its busy flag set when a call raises
            self.fault = f"serial port {self.port_name} failed ({what}: {_port_error(exc)})"
            raise PortLost(f"bus on {self.port_name}: {self.fault}; torque is off as far as "
                           f"the bus allows; reset (or configure another port) to recover"
                           ) from None
        except Exception as exc:
            port.is_using = False
            raise CommunicationError(f"{what}: the SDK failed: {type(exc).__name__}: {exc}",
                                     self.ids) from None

    # -- single-servo access ---------------------------------------------------------------
    def ping(self, servo_id: int) -> tuple[int, int] | None:
        """(model number, firmware version), or None when nothing answers."""
        port = self._require()
        data, result, error = self._sdk("ping", self._ph.readTxRx, port, servo_id, 0, 7)
        if result != COMM_SUCCESS:
            return None
        return data[0] | data[1] << 8, data[6]

    def scan(self, ids: Iterable[int] | None = None) -> dict[int, tuple[int, int]]:
        """Servos present on the bus: {id: (model, firmware)} (broadcast ping, else one by one)."""
        port = self._require()
        found, result = self._sdk("scan", self._ph.broadcastPing, port)
        if result == COMM_SUCCESS and found:
            return {sid: (model, fw) for sid, (model, fw) in sorted(found.items())}
        out = {}
        for sid in ids if ids is not None else range(253):
            info = self.ping(sid)
            if info is not None:
                out[sid] = info
        return out

    def _patient(self, what: str, call: Callable[..., Any], *args: Any) -> Any:
        """One exchange outside the control cycle (`call(port, *args)`, which returns its
        result code second to last), tried up to `SETUP_ATTEMPTS` times while it times
        out. A late reply to an attempt given up on is drained before anything else is
        sent (the port settles after a miss), and so is one after a retry that answered: it
        may have been the late reply, of the same shape, its own still coming (on a loaded
        host a write's late status was read back as a register's value, "return_delay_time
        reads 161 after writing 0", its CRC byte)."""
        for attempt in range(SETUP_ATTEMPTS):
            out = self._sdk(what, call, self._require(), *args)
            if out[-2] not in RX_TIMEOUT_RESULTS:
                if attempt:  # that answer may have been an earlier attempt's: this one's next
                    self._drain()
                break
        return out

    def read(self, servo_id: int, name: str) -> int:
        """Read one control-table item (raw value)."""
        reg = REG[name]
        data, result, error = self._patient(f"read {name}", self._ph.readTxRx, servo_id,
                                            reg.address, reg.size)
        self._check(result, error, (servo_id,), f"read {name}")
        return reg.decode(bytes(data))

    def write(self, servo_id: int, name: str, value: int) -> None:
        """Write one control-table item (raw value), checked by the servo's status."""
        reg = REG[name]
        result, error = self._patient(f"write {name}", self._ph.writeTxRx, servo_id,
                                      reg.address, reg.size, list(reg.encode(value)))
        self._check(result, error, (servo_id,), f"write {name}={value}")

    def reboot(self, servo_id: int) -> None:
        result, error = self._sdk("reboot", self._ph.reboot, self._require(), servo_id)
        self._check(result, error & ~ALERT_BIT, (servo_id,), "reboot")

    def _check(self, result: int, error: int, ids: tuple[int, ...], what: str) -> None:
        if result != COMM_SUCCESS:
            cls = BusTimeoutError if result in RX_TIMEOUT_RESULTS else CommunicationError
            raise cls(f"servo {ids[0]}: {what}: {_result_words(self._ph, result)}", ids)
        if error & 0x7F:
            raise CommunicationError(f"servo {ids[0]}: {what}: {describe_status_error(error)}",
                                     ids)

    # -- configuration ---------------------------------------------------------------------
    def configure(self, settings: dict[str, int], *, verify: bool = False) -> None:
        """Write the same raw settings to every servo (EEPROM items need torque off); with
        `verify`, read each back and raise if a servo does not hold it."""
        for sid in self.ids:
            for name, value in settings.items():
                if self.read(sid, name) != value:
                    self.write(sid, name, value)
                    if verify and (got := self.read(sid, name)) != value:
                        raise CommunicationError(f"servo {sid}: {name} reads {got} after "
                                                 f"writing {value}", (sid,))

    def detect_fast_read(self) -> bool:
        """Use Fast Sync Read only if every servo's firmware supports it and it answers."""
        fast = self.use_fast_read
        for sid in self.ids:
            info = self.ping(sid)
            if info is None:
                raise BusTimeoutError(f"servo {sid} does not answer a ping on {self.port_name}",
                                      (sid,))
            fast = fast and info[1] >= FAST_READ_MIN_FIRMWARE
        if fast:
            try:
                self._anchor(self._fast_sync_read())
            except CommunicationError:
                fast = False
        self.stats.fast_read = fast
        if not fast:
            self._anchor()
        return fast

    def _anchor(self, readings: dict[int, ServoReading] | None = None) -> None:
        """Take each servo's clock against ours afresh from a read outside the control
        cycle (patient, so likely prompt: the floor is tightest from a reply that came at
        once), `readings` if given; best effort: a servo missed here is dated from its
        first cycle's reply on."""
        self._ages.forget()
        if readings is None:
            try:
                readings = self._fast_sync_read() if self.stats.fast_read else self._sync_read()
            except CommunicationError:
                return
        for sid, reading in readings.items():
            self._ages.age_ms(sid, reading.tick, self._asked_ns, self._received_ns)

    def torque(self, on: bool, *, best_effort: bool = False) -> None:
        """Torque on or off for every servo (one Sync Write)."""
        if best_effort and (self._port is None or (not on and self.diagnosing)):
            return  # nothing to send on; or the latch sent it before the diagnosis began
        port = self._require()
        writer = GroupSyncWrite(port, self._ph, REG["torque_enable"].address, 1)
        for sid in self.ids:
            writer.addParam(sid, [int(on)])
        if not on:
            self.torque_on = False
        try:
            result = self._sdk(f"torque {'on' if on else 'off'}", writer.txPacket)
        except FirmwareError:
            if best_effort:  # the adapter is gone: nothing more can be sent
                return
            raise
        if result != COMM_SUCCESS and not best_effort:
            raise CommunicationError(f"torque {'on' if on else 'off'}: "
                                     f"{_result_words(self._ph, result)}", self.ids)
        self.torque_on = on

    # -- the control cycle -----------------------------------------------------------------
    def cycle(self, goals: dict[int, int] | None = None) -> dict[int, ServoReading]:
        """One Sync Read of every servo, then one Sync Write of `goals` (ticks), if any.

        Raises CommunicationError on a failed read (counted), HardwareFault once
        `failure_tolerance` consecutive cycles failed or a servo reports a hardware error.
        """
        if self.fault:
            raise HardwareFault(f"bus faulted: {self.fault}; reset first")
        t0 = time.monotonic_ns()
        try:
            with self._cycle_timing():
                readings = self._fast_sync_read() if self.stats.fast_read else self._sync_read()
            self._fresh(readings)
        except CommunicationError as exc:
            self.stats.failures += 1
            self.stats.consecutive_failures += 1
            if self.stats.consecutive_failures >= self.failure_tolerance:
                self._latch(f"{self.stats.consecutive_failures} consecutive failed cycles "
                            f"(last: {exc})",
                            explain=functools.partial(why_cycles_failed, self, exc))
            raise
        self.stats.consecutive_failures = 0
        alerts = [sid for sid, r in readings.items() if r.error & ALERT_BIT]
        if alerts:
            detail = []
            for sid in alerts:
                try:
                    bits = self.read(sid, "hardware_error_status")
                    detail.append(f"servo {sid}: {describe_hardware_error(bits) or 'alert'}")
                except CommunicationError:
                    detail.append(f"servo {sid}: alert")
            self._latch("; ".join(detail) + " (find out why before you reset: the load, the "
                        "temperature, the supply voltage)")
        if self.torque_on and self.stats.cycles % TORQUE_CHECK_CYCLES == 0:
            self.check_torque()
        if goals:
            self.write_goals(goals)
        self.stats.cycles += 1
        self.stats.last_cycle_ns = time.monotonic_ns() - t0
        return readings

    def _fresh(self, readings: dict[int, ServoReading]) -> None:
        """Raise StaleReplyError if a reply was made before this cycle asked for it."""
        ages = {sid: self._ages.age_ms(sid, r.tick, self._asked_ns, self._received_ns)
                for sid, r in readings.items()}
        stale = {sid: age for sid, age in ages.items() if age > STALE_MS}
        if stale:
            told = ", ".join(f"servo {sid}: {age:.0f} ms" for sid, age in stale.items())
            raise StaleReplyError(
                f"{'fast ' if self.stats.fast_read else ''}sync read: replies made before "
                f"the read asked for them ({told} before): late answers to an earlier cycle",
                tuple(stale))

    def write_goals(self, goals: dict[int, int]) -> None:
        writer = GroupSyncWrite(self._require(), self._ph, REG["goal_position"].address, 4)
        for sid, ticks in goals.items():
            writer.addParam(sid, list(REG["goal_position"].encode(ticks)))
        result = self._sdk("sync write of goals", writer.txPacket)
        if result != COMM_SUCCESS:
            raise CommunicationError(f"sync write of goals: {_result_words(self._ph, result)}",
                                     tuple(goals))

    def _sync_read(self) -> dict[int, ServoReading]:
        port = self._require()
        self._asked_ns = time.monotonic_ns()  # as it goes out: its own replies are younger
        result = self._sdk("sync read", self._ph.syncReadTx, port, SYNC_READ_START,
                           SYNC_READ_LENGTH, list(self.ids), len(self.ids), False)
        if result != COMM_SUCCESS:
            raise CommunicationError(f"sync read: {_result_words(self._ph, result)}", self.ids)
        out = {}
        for sid in self.ids:
            data, result, error = self._sdk("sync read", self._ph.readRx, port, sid,
                                            SYNC_READ_LENGTH)
            if result != COMM_SUCCESS:
                cls = BusTimeoutError if result in RX_TIMEOUT_RESULTS else CommunicationError
                raise cls(f"sync read: servo {sid}: {_result_words(self._ph, result)}", (sid,))
            out[sid] = _reading(bytes(data), error)
        self._received_ns = time.monotonic_ns()
        return out

    def _fast_sync_read(self) -> dict[int, ServoReading]:
        port = self._require()
        self._asked_ns = time.monotonic_ns()  # as it goes out: its own replies are younger
        result = self._sdk("fast sync read", self._ph.syncReadTx, port, SYNC_READ_START,
                           SYNC_READ_LENGTH, list(self.ids), len(self.ids), True)
        if result != COMM_SUCCESS:
            raise CommunicationError(f"fast sync read: {_result_words(self._ph, result)}",
                                     self.ids)
        rx, result = self._sdk("fast sync read", self._ph.rxPacket, port, True)
        parts = [(sid, SYNC_READ_LENGTH) for sid in self.ids]
        if result != COMM_SUCCESS:
            cls = BusTimeoutError if result in RX_TIMEOUT_RESULTS else CommunicationError
            damaged = first_damaged(bytes(rx), parts)  # a whole reply, spoiled in one part
            where = "" if damaged is None else f" (damaged from servo {damaged}'s part on)"
            raise cls(f"fast sync read: {_result_words(self._ph, result)}{where}",
                      self.ids if damaged is None else (damaged,), bytes(rx))
        self._received_ns = time.monotonic_ns()
        try:
            decoded = split_fast_read(bytes(rx), parts)
        except PacketError as exc:
            raise CommunicationError(f"fast sync read: {exc}", self.ids, bytes(rx)) from None
        return {sid: _reading(data, error) for sid, (error, data) in decoded.items()}

    def check_torque(self, *, patient: bool = False) -> None:
        """Latch a fault if a servo's torque went off by itself (one Sync Read of Torque
        Enable). A read that fails says nothing: the control cycle's own read counts those.
        `patient`: each reply may take the setup's timeout, not half a cycle (once, where
        the answer decides between a fault and a drop)."""
        address, ids = REG["torque_enable"].address, list(self.ids)
        try:
            with self._cycle_timing(patient=patient) as port:
                off = self._torque_off(port, address, ids)
        except CommunicationError:
            return
        if off:
            self._latch(f"servo {', '.join(map(str, off))} lost torque by itself (it "
                        "restarted: a brown-out? check its power supply and cable)")

    def _torque_off(self, port: PacedPortHandler, address: int, ids: list[int]) -> list[int]:
        """Servos whose Torque Enable reads 0 (one Sync Read); [] when a reply is missing."""
        if self._sdk("torque check", self._ph.syncReadTx, port, address, 1, ids, len(ids),
                     False) != COMM_SUCCESS:
            return []
        off = []
        for sid in ids:
            data, result, _ = self._sdk("torque check", self._ph.readRx, port, sid, 1)
            if result != COMM_SUCCESS:
                return []
            if not data[0]:
                off.append(sid)
        return off

    @contextlib.contextmanager
    def _cycle_timing(self, *, patient: bool = False) -> Iterator[PacedPortHandler]:
        """The port timed for the control cycle: each reply waits half the cycle's budget
        (`patient`: the setup's timeout), and a miss is not settled (it cannot wait for a
        late reply); the setup's timing and settling again after."""
        port = self._require()
        port.budget_ms = SETUP_TIMEOUT_MS if patient else self.cycle_budget_s * 1e3 / 2
        port.settles = False
        try:
            yield port
        finally:
            port.budget_ms, port.settles = SETUP_TIMEOUT_MS, True

    def _drain(self, quiet_s: float = SETUP_TIMEOUT_MS / 1e3, cap_s: float = 0.25) -> None:
        """Read and drop what arrives until the line has been quiet for `quiet_s` (at most
        `cap_s`): replies to requests given up on, which would land in the next one's."""
        self._require().settle(quiet_s * 1e3, cap_s * 1e3)

    def _latch(self, reason: str, explain: Callable[[], str] | None = None) -> None:
        """Latch `reason` as the fault and send torque off, then add what `explain` (which
        may take a few timeouts) finds to the fault's words: at once, or on a thread of its
        own (`diagnose_in_background`)."""
        self.fault = reason
        self.torque(False, best_effort=True)
        if explain is not None and self.diagnose_in_background:
            self.diagnosed = None
            self._diagnosis = threading.Thread(target=self._diagnose, args=(reason, explain),
                                               name="bus-diagnosis", daemon=True)
            self._diagnosis.start()
            raise HardwareFault(self._fault_message(reason))
        if explain is not None:
            self.fault = reason + explain()
        raise HardwareFault(self._fault_message(self.fault))

    def _fault_message(self, fault: str) -> str:
        # torque off goes out by sync write, which no servo acknowledges: say it was sent
        return (f"bus on {self.port_name}: {fault}; torque off sent to every servo, reset to "
                "recover")

    def _diagnose(self, reason: str, explain: Callable[[], str]) -> None:
        """The background diagnosis: `explain`'s words join the fault (`diagnosed`)."""
        try:
            words = explain()
        except Exception as exc:  # a diagnosis never takes the fault's own words away
            words = f"; (asking the servos why failed: {type(exc).__name__}: {exc})"
        self.fault = reason + words
        self.diagnosed = (self._fault_message(reason), self._fault_message(self.fault))

    def reset(self) -> list[str]:
        """Clear a latched fault: reboot servos that report a hardware error (their RAM
        returns to defaults: the caller configures them again), count afresh. Returns a
        line for each servo rebooted: its error may be news (one that arose while another
        fault was latched was reported by nothing else)."""
        rebooted = []
        for sid in self.ids:
            try:
                if bits := self.read(sid, "hardware_error_status"):
                    self.reboot(sid)
                    rebooted.append(f"servo {sid} reported {describe_hardware_error(bits)}: "
                                    "rebooted it (find out why before you activate)")
            except CommunicationError:
                pass
        self.fault = None
        self.stats.consecutive_failures = 0
        self._anchor()  # a rebooted servo's clock starts again
        return rebooted


def _port_error(exc: BaseException) -> str:
    """A port error in one form whichever layer raised it: termios.error carries (errno,
    text) and printed "(5, 'Input/output error')" where an OSError printed "[Errno 5]
    Input/output error" (the same lost port, a finger's and a hand's words, a held-out
    campaign)."""
    args = exc.args
    if not isinstance(exc, OSError) and len(args) == 2 and isinstance(args[0], int):
        return f"[Errno {args[0]}] {args[1]}"
    return str(exc)


def _reading(data: bytes, error: int) -> ServoReading:
    base = SYNC_READ_START
    return ServoReading(
        position=REG["present_position"].decode(data[132 - base:136 - base]),
        velocity=REG["present_velocity"].decode(data[128 - base:132 - base]),
        current=REG["present_current"].decode(data[126 - base:128 - base]),
        error=error,
        tick=REG["realtime_tick"].decode(data[120 - base:122 - base]))


__all__ = ["BROADCAST_ID", "BusStats", "DxlBus", "ServoReading"]
