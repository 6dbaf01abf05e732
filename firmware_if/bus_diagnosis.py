"""Why a bus's cycles failed, in words for its fault: which servos answer a ping late, or
not at all, or whether the host missed the cycles or the replies came damaged.

It runs once, when `DxlBus` latches a fault after its consecutive failed cycles, and may
take a few timeouts: a late servo's replies may still be on the line.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from dynamixel_sdk.protocol2_packet_handler import PKT_ID
from dynamixel_sdk.robotis_def import COMM_RX_CORRUPT, COMM_SUCCESS

from firmware_if.errors import BusTimeoutError, CommunicationError, FirmwareError, PortLost
from firmware_if.packets import INST_PING, packet
from firmware_if.sdk_fixes import (
    PING_ANSWER_LENGTH,
    PORT_ERRORS,
    RX_TIMEOUT_RESULTS,
    SETUP_TIMEOUT_MS,
    answers,
)

if TYPE_CHECKING:
    from firmware_if.dxl_bus import DxlBus

LATE_LIMIT_S = 0.6
"""How long a fault's diagnosis waits for a ping's answer, and for a line busy with late
replies to fall quiet: a servo answering later is called silent (the emulator's `late`
drills go to 0.5 s; a USB adapter's latency timer is 16 ms by default)."""
LATE_CAP_S = 5.0
"""The most one wait of the diagnosis lasts while replies keep coming (a babbling line)."""


def why_cycles_failed(bus: DxlBus, last: CommunicationError) -> str:
    """Which servos do not answer a ping, or answer it late, as words for a fault (one
    silent servo spoils a sync read of all: the read alone cannot say which). A late
    servo's replies may still be on the bus, and a ping waits behind them (a half-duplex
    line, or the emulator, answers one request at a time): cut short, it blamed healthy
    servos ("no servo answers" for `late 2 0.5`). So every ping's answer is waited for
    up to `LATE_LIMIT_S`, and a servo that answered late is pinged again once the line
    is clear, to time its own answer. Every servo answering in time says the host, not
    the bus, missed the cycles. It runs once, in the tick that latches the fault, after
    torque off has gone out."""
    bus._require()  # a closed port is the caller's error, not a silent bus
    half_cycle_ms = bus.cycle_budget_s * 1e3 / 2  # what a cycle's read waits
    damaged: set[int] = set()
    try:
        bus._drain()  # the failed cycles' replies, already coming
        answered = answer_times(bus, damaged=damaged)
    except (PortLost, *PORT_ERRORS, ValueError) as exc:  # the port itself failed
        words = bus.fault if isinstance(exc, PortLost) else f"{type(exc).__name__}: {exc}"
        return (f"; then the serial port itself failed ({words}): its adapter unplugged, "
                "or the emulator stopped? Reconnect it, then reset (or configure another "
                "port)")
    except FirmwareError:
        return ""
    late = {sid: ms for sid, ms in answered.items() if ms > half_cycle_ms}
    silent = [sid for sid in bus.ids if sid not in answered]
    if not late and not silent and isinstance(last, BusTimeoutError):
        return ("; every servo answers a ping in time now: the host missed the cycles "
                "(a loaded machine? the loop's scheduling is in `haptic ctl status`)")
    if not late and not silent:  # the replies came, damaged
        where = (f", first in servo {last.servo_ids[0]}'s reply (its cable, or one "
                 "between it and the adapter)" if len(last.servo_ids) == 1 else "")
        return (f"; every servo answers a ping now, but the cycles' replies came damaged"
                f"{where}: a noisy or loose cable or connector, or a baud too fast for "
                "the cable")
    return (_late_words(late, bus.cycle_budget_s)
            + _silent_words(silent, len(bus.ids), bus.baud, damaged))

def answer_times(bus: DxlBus, tries: int = 3, damaged: set[int] | None = None
                 ) -> dict[int, float]:
    """{id: ms from its ping to its answer} for every servo that answers. One that answers
    later than a cycle's read waits is timed again alone, on a quiet line, keeping its
    quickest: a late servo is as late again, and is timed no more; one that only waited
    behind another's late replies, or met a host's hiccup, comes sooner, and is timed up
    to `tries` times (under load, a healthy servo timed once more at 15 ms was named late
    beside the late one). `damaged` gathers the servos whose answers came damaged."""
    answered = ping_times(bus, bus.ids, damaged)
    half_cycle_ms = bus.cycle_budget_s * 1e3 / 2
    for sid in [s for s, ms in answered.items() if ms > half_cycle_ms]:
        for _ in range(tries):
            before = answered[sid]
            answered[sid] = min(before, ping_times(bus, (sid,)).get(sid, before))
            if answered[sid] <= half_cycle_ms or answered[sid] >= before / 2:
                break
    return answered


def late_words(bus: DxlBus) -> str:
    """What keeps the servos from answering a cycle's read in time (late or silent servos,
    in a fault's words, without the leading "; "), or "" when every one does: a reset
    checks it (a held-out check: with a servo answering after 10 ms, `reset` answered ok
    and the bus faulted again 0.2 s later)."""
    damaged: set[int] = set()
    answered = answer_times(bus, damaged=damaged)
    late = {sid: ms for sid, ms in answered.items() if ms > bus.cycle_budget_s * 1e3 / 2}
    silent = [sid for sid in bus.ids if sid not in answered]
    return (_late_words(late, bus.cycle_budget_s)
            + _silent_words(silent, len(bus.ids), bus.baud, damaged)).removeprefix("; ")


def ping_times(bus: DxlBus, ids: Sequence[int], damaged: set[int] | None = None
               ) -> dict[int, float]:
    """Ping `ids`: {id: ms from its ping to its answer} for those that answer. Each ping
    gets the setup's timeout (or its answer) before the next goes out; answers that come
    later still count, told apart by id and shape, until all have come or the line has
    been quiet for `LATE_LIMIT_S` (a reply later than that is none). `damaged` gathers
    the ids of answers that came with a bad checksum."""
    port = bus._require()
    sent: dict[int, int] = {}
    got: dict[int, float] = {}
    for sid in ids:
        sent[sid] = time.monotonic_ns()  # before the write: a host descheduled after it
        # not txPacket: it would settle, dropping the answers still awaited; through the
        # bus's guard, so a port that fails here is PortLost (a held-out client's kill
        # during a reset's check was answered `internal`: a SerialException)
        bus._sdk("ping", port.writePort, list(packet(sid, INST_PING)))
        _take_answers(bus, sent, got, SETUP_TIMEOUT_MS, until=sid, damaged=damaged)
    _take_answers(bus, sent, got, LATE_LIMIT_S * 1e3, damaged=damaged)
    return got

def _take_answers(bus: DxlBus, sent: dict[int, int], got: dict[int, float], wait_ms: float,
                  until: int | None = None, damaged: set[int] | None = None) -> None:
    """Read status packets into `got` (answers to the pings `sent`) until `until` has
    answered within `wait_ms` of its ping, or (no `until`) every ping has answered or no
    status has come for `wait_ms`, at most `LATE_CAP_S`."""
    port = bus._require()
    cap = time.monotonic_ns() + LATE_CAP_S * 1e9
    while not (until in got if until is not None else got.keys() >= sent.keys()):
        left = (wait_ms if until is None
                else wait_ms - (time.monotonic_ns() - sent[until]) / 1e6)
        left = min(left, (cap - time.monotonic_ns()) / 1e6)
        if left <= 0:
            return
        port.setPacketTimeoutMillis(left)
        rx, result = bus._sdk("ping", bus._ph.rxPacket, port, False)
        if result in RX_TIMEOUT_RESULTS:
            return
        if result == COMM_RX_CORRUPT and damaged is not None and len(rx) > PKT_ID \
                and rx[PKT_ID] in sent:
            damaged.add(rx[PKT_ID])  # its reply, with a spoiled checksum or cut short
        if result == COMM_SUCCESS and rx[PKT_ID] in sent and rx[PKT_ID] not in got \
                and answers(rx, rx[PKT_ID], PING_ANSWER_LENGTH):
            got[rx[PKT_ID]] = (time.monotonic_ns() - sent[rx[PKT_ID]]) / 1e6


def _late_words(late: dict[int, float], cycle_budget_s: float) -> str:
    """A fault's words for servos that answer a ping, but later than a cycle's read waits
    (half the cycle's budget)."""
    if not late:
        return ""
    who = (f"servo {next(iter(late))} answers" if len(late) == 1
           else f"servos {', '.join(map(str, late))} answer")
    return (f"; {who} a ping only after {max(late.values()):.0f} ms (a cycle's read waits "
            f"{cycle_budget_s * 1e3 / 2:g} ms): a slow adapter or a loaded host (a USB "
            "adapter's latency timer, 16 ms by default on FTDI, should be 1 ms: `haptic bus "
            "check` tells)")


def _silent_words(silent: list[int], servos: int, baud: int,
                  damaged: set[int] | frozenset[int] = frozenset()) -> str:
    """A fault's words for servos that answer no ping at all, or whose every answer came
    damaged (a held-out check's `corrupt 2 100000` was told "does not answer a ping:
    check its cable and power")."""
    spoiled = [sid for sid in silent if sid in damaged]
    if spoiled:
        one = len(spoiled) == 1
        who = (f"servo {spoiled[0]} answers" if one
               else f"servos {', '.join(map(str, spoiled))} answer")
        cable, them = ("a noisy or loose cable or connector", "it") if one else (
            "noisy or loose cables or connectors", "them")
        rest = [sid for sid in silent if sid not in damaged]
        return (f"; {who} a ping only with damaged replies (bad checksums, or cut short): "
                f"{cable} between {them} and the adapter, or a baud too fast for the "
                f"cable{'' if one else 's'}" + _silent_words(rest, servos, baud))
    if not silent:
        return ""
    if len(silent) == servos:
        return (f"; no servo answers a ping: check the bus power, the adapter, and that the "
                f"servos use {baud} baud")
    if len(silent) == 1:
        return f"; servo {silent[0]} does not answer a ping: check its cable and power"
    return (f"; servos {', '.join(map(str, silent))} do not answer a ping: check their "
            "cables and power")
