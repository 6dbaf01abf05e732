"""`haptic bus scan|read|check|release`: look at a Dynamixel bus before trusting a run to it,
and let its servos go when nothing else can."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.dxl_bus import FAST_READ_MIN_FIRMWARE, DxlBus, ServoReading
from firmware_if.errors import CommunicationError
from firmware_if.hand import Finger, Hand, load_hand, presets
from firmware_if.registers import (
    BAUD_RATES,
    BAUD_REGISTER,
    CURRENT_BASED_POSITION,
    MODELS,
    OPERATING_MODES,
    ticks_to_rad,
)
from tools.arg_types import integer, number
from tools.signals import signals_held

MODEL_NAMES = {number: name for name, (number, _) in MODELS.items()}


def register(p: argparse.ArgumentParser) -> None:
    p.description = ("Look at a Dynamixel servo bus before trusting a run to it: which servos "
                     "answer, their live joint angles, their configuration; and turn their "
                     "torque off when the process that drove them is gone.")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    scan = verbs.add_parser("scan", help="find the servos on a port")
    _port_options(scan)
    scan.set_defaults(handler=cmd_scan)
    read = verbs.add_parser("read", help="joint angles and fingertip centre, live")
    _port_options(read, hand=True)
    read.add_argument("--count", type=integer(1, 10**9), default=None, metavar="N",
                      help="stop after N readings (default: until Ctrl-C)")
    read.add_argument("--interval", type=number(0.0, 3600, "s"), default=0.1, metavar="S",
                      help="seconds between readings (default: %(default)s)")
    read.set_defaults(handler=cmd_read)
    check = verbs.add_parser("check", help="configuration sanity: latency timer, return "
                                           "delay, baud, modes")
    _port_options(check, hand=True)
    check.set_defaults(handler=cmd_check)
    release = verbs.add_parser(
        "release", help="turn every servo's torque off (a daemon killed outright, or a "
                        "crashed host, leaves the servos holding their last goal)")
    _port_options(release)
    release.add_argument("--hand", metavar="PRESET|FILE",
                         help="only this hand's servos (default: every servo that answers)")
    release.set_defaults(handler=cmd_release)


def _port_options(p: argparse.ArgumentParser, hand: bool = False) -> None:
    p.add_argument("--port", required=True, help="serial port, e.g. /dev/ttyUSB0")
    p.add_argument("--baud", type=int, default=None, choices=sorted(BAUD_REGISTER),
                   metavar="BPS", help="baud rate, one of the servos' "
                   f"({', '.join(map(str, sorted(BAUD_REGISTER)))}; default: the hand's, "
                   "else 1000000)")
    if hand:
        p.add_argument("--hand", required=True, metavar="PRESET|FILE",
                       help=f"hand preset ({', '.join(presets())}) or TOML file")


def _bus(args: argparse.Namespace, hand: Hand | None, ids: tuple[int, ...] = (1,)) -> DxlBus:
    baud = args.baud or (hand.baud if hand else 1_000_000)
    return DxlBus(args.port, hand.ids if hand else ids, baud=baud)


def cmd_scan(args: argparse.Namespace) -> int:
    with _bus(args, None) as bus:
        found = bus.scan()
    if not found:
        print(f"no servo answered on {args.port}")
        return 1
    for sid, (model, firmware) in found.items():
        print(f"id {sid:3d}: {MODEL_NAMES.get(model, f'model {model}')}, firmware {firmware}")
    return 0


def cmd_read(args: argparse.Namespace) -> int:
    hand = load_hand(args.hand)
    with _bus(args, hand) as bus:
        bus.detect_fast_read()
        n = 0
        next_t = time.monotonic()
        while args.count is None or n < args.count:
            with signals_held():  # Ctrl-C between exchanges, never inside one
                try:
                    readings = bus.cycle()
                except CommunicationError as exc:  # a missed cycle; a latched fault ends it
                    readings = None
                    print(f"# cycle {n + 1} missed: {exc}", file=sys.stderr, flush=True)
            if readings is not None:
                print("  ||  ".join(_finger_line(f, readings) for f in hand.fingers),
                      flush=True)
            n += 1
            next_t += args.interval
            time.sleep(max(0.0, next_t - time.monotonic()))
    return 0


def _finger_line(finger: Finger, readings: dict[int, ServoReading]) -> str:
    """One finger's joint angles and fingertip centre (hand frame) from one bus cycle."""
    q = np.array([ticks_to_rad(readings[j.id].position, j.zero_ticks, j.direction)
                  for j in finger.joints])
    centre = kin.forward(finger, q)
    joints = " ".join(f"{j.name}={np.degrees(a):7.2f}" for j, a in
                      zip(finger.joints, q, strict=True))
    return (f"{joints} deg | centre x={centre[0] * 1e3:8.2f} y={centre[1] * 1e3:8.2f} "
            f"z={centre[2] * 1e3:8.2f} mm")


def latency_timer(port: str) -> int | None:
    """The USB adapter's latency timer in ms (FTDI on Linux), or None if not applicable."""
    name = Path(port).resolve().name
    path = Path(f"/sys/bus/usb-serial/devices/{name}/latency_timer")
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def check_lines(bus: DxlBus, hand: Hand, port: str) -> list[tuple[str, str]]:
    """(level, message) findings: level is 'ok', 'warn' or 'FAIL'."""
    out: list[tuple[str, str]] = []
    timer = latency_timer(port)
    if timer is None:
        out.append(("ok", f"{port}: no USB latency timer (not an FTDI adapter)"))
    elif timer > 1:
        out.append(("warn", f"latency timer {timer} ms adds up to {timer} ms per packet; "
                            f"echo 1 > /sys/bus/usb-serial/devices/{Path(port).name}/"
                            "latency_timer"))
    else:
        out.append(("ok", f"latency timer {timer} ms"))
    baud_reg = BAUD_REGISTER.get(hand.baud)
    for sid in hand.ids:
        info = bus.ping(sid)
        if info is None:
            out.append(("FAIL", f"servo {sid}: no answer"))
            continue
        model, firmware = info
        name = MODEL_NAMES.get(model, f"model {model}")
        out.append(("ok" if model in MODEL_NAMES else "warn", f"servo {sid}: {name}, "
                    f"firmware {firmware}"))
        if firmware < FAST_READ_MIN_FIRMWARE:
            out.append(("warn", f"servo {sid}: firmware {firmware} has no Fast Sync Read; "
                                "plain Sync Read will be used"))
        try:
            values = {name: bus.read(sid, name) for name in
                      ("baud_rate", "return_delay_time", "status_return_level",
                       "operating_mode", "hardware_error_status", "torque_enable")}
        except CommunicationError as exc:
            out.append(("FAIL", f"servo {sid}: {exc}"))
            continue
        if values["baud_rate"] != baud_reg:
            out.append(("FAIL", f"servo {sid}: baud register {values['baud_rate']} "
                                f"({BAUD_RATES.get(values['baud_rate'])} bps) but the hand "
                                f"says {hand.baud}"))
        delay_us = 2 * values["return_delay_time"]
        out.append(("ok" if delay_us <= hand.return_delay_us else "warn",
                    f"servo {sid}: return delay {delay_us} us"
                    + ("" if delay_us <= hand.return_delay_us else
                       f" (the driver sets {hand.return_delay_us} us on open)")))
        mode = values["operating_mode"]
        out.append(("ok" if mode == CURRENT_BASED_POSITION else "warn",
                    f"servo {sid}: operating mode {mode} ({OPERATING_MODES.get(mode, '?')})"
                    + ("" if mode == CURRENT_BASED_POSITION else
                       "; the driver switches to 5 (current-based position) on open")))
        if values["status_return_level"] != 2:
            out.append(("warn", f"servo {sid}: status return level "
                                f"{values['status_return_level']}; writes will not be "
                                "confirmed until the driver sets 2"))
        out.append(("ok", f"servo {sid}: torque off") if not values["torque_enable"] else
                   ("warn", f"servo {sid}: torque on, though nothing drives it (the port is "
                            "ours): it holds its position until a driver opens the bus and "
                            "turns it off, or `haptic bus release` does"))
        if values["hardware_error_status"]:
            out.append(("FAIL", f"servo {sid}: hardware error status "
                                f"{values['hardware_error_status']:#04x}; reboot it"))
    return out


def cmd_check(args: argparse.Namespace) -> int:
    hand = load_hand(args.hand)
    with _bus(args, hand) as bus:
        lines = check_lines(bus, hand, args.port)
    for level, message in lines:
        print(f"{level:4s} {message}")
    return 1 if any(level == "FAIL" for level, _ in lines) else 0


def cmd_release(args: argparse.Namespace) -> int:
    """Torque off for every servo, each read back. Nothing else does it once the driver
    is gone: SIGKILL gives a daemon no chance to, and a servo holds its goal with torque
    on for as long as it has power (a held object stays held until then)."""
    hand = load_hand(args.hand) if args.hand else None
    with _bus(args, hand) as bus:
        answered = tuple(bus.scan())
        ids = hand.ids if hand else answered
        if not ids:
            print(f"no servo answered on {args.port}")
            return 1
        bus.ids = ids
        bus.torque(False)
        still = []
        for sid in ids:
            try:
                on = bus.read(sid, "torque_enable")
            except CommunicationError as exc:
                print(f"servo {sid}: no answer to the read-back ({exc})")
                still.append(sid)
                continue
            print(f"servo {sid}: torque {'ON' if on else 'off'}")
            if on:
                still.append(sid)
    others = sorted(set(answered) - set(ids))
    if others:  # another hand's servos, or the wrong hand file: not ours to leave on
        print(f"servo {', '.join(map(str, others))} also answered, which hand '{hand.name}' "
              "does not use: left as they were (release without --hand turns off every "
              "servo that answers)", file=sys.stderr)
    if hand is None:  # a servo that did not answer the scan was not released
        print(f"{len(ids)} servo(s) answered; one that did not (muted, unpowered) was not "
              "released: give --hand to check each of a hand's servos", file=sys.stderr)
    if still:
        print(f"torque may still be on: servo {', '.join(map(str, still))}; check the cable "
              "and power, then run release again", file=sys.stderr)
        return 1
    return 0
