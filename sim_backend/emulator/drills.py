"""Fault drills on a running emulator: one line of text, one fault, one line of answer.

`haptic emulate` reads these from its standard input, so a lab can rehearse what the
daemon does when a servo stops answering, overheats or restarts, by typing (or piping)
them beside a running `hapticd`:

    mute ID | unmute ID        never reply / reply again (an unplugged servo)
    drop ID N                  swallow the next N replies
    corrupt ID N               spoil the checksum of the next N replies
    late ID SECONDS            delay every reply (0 to stop; an adapter's latency timer)
    error ID KIND[,KIND]       latch a hardware error: overload, overheating, voltage,
                               encoder, shock (the shutdown ones turn its torque off)
    reboot ID                  restart by itself, as on a brown-out (torque off, RAM reset)
    clear ID                   no more injected reply faults on that servo
    help

A bad line changes nothing and says what is wrong.
"""

from __future__ import annotations

from firmware_if.registers import HARDWARE_ERRORS
from sim_backend.emulator.bus import ServoBus

ERRORS = {"voltage": 0, "overheating": 2, "encoder": 3, "shock": 4, "overload": 5}
"""Hardware error names a drill takes -> Hardware Error Status bit (`HARDWARE_ERRORS`)."""
assert sorted(ERRORS.values()) == sorted(HARDWARE_ERRORS)
HELP = ("mute ID | unmute ID | drop ID N | corrupt ID N | late ID SECONDS | "
        f"error ID {','.join(ERRORS)} | reboot ID | clear ID | help")


class DrillError(ValueError):
    """A drill line that names no fault this emulator can make."""


def drill(bus: ServoBus, line: str) -> str:
    """Apply one drill line to `bus`; the answer in words. Raises DrillError (and changes
    nothing) for a line it cannot apply."""
    words = line.split()
    if not words or words[0] == "help":
        return HELP
    verb, args = words[0], words[1:]
    arity = {"mute": 1, "unmute": 1, "drop": 2, "corrupt": 2, "late": 2, "error": 2,
             "reboot": 1, "clear": 1}
    if verb not in arity:
        raise DrillError(f"unknown drill '{verb}'; one of: {HELP}")
    if len(args) != arity[verb]:
        raise DrillError(f"'{verb}' takes {arity[verb]} value(s), got {len(args)}: {HELP}")
    servo = _servo(bus, args[0])
    parse = {"drop": _count, "corrupt": _count, "late": _seconds, "error": _error_bits}
    value = parse[verb](args[1], verb) if verb in parse else None  # before any change
    with bus.lock:
        if verb in ("mute", "unmute"):
            bus.fault(servo).mute = verb == "mute"
        elif verb in ("drop", "corrupt"):
            setattr(bus.fault(servo), verb, value)
        elif verb == "late":
            bus.fault(servo).late_s = value
        elif verb == "error":
            bus.inject_hardware_error(servo, value)
        elif verb == "reboot":
            bus.servos[servo].reboot()
        else:
            bus.faults.pop(servo, None)
    return f"ok: {' '.join(words)}"


def _servo(bus: ServoBus, text: str) -> int:
    try:
        servo = int(text)
    except ValueError:
        raise DrillError(f"servo id must be a whole number, got '{text}'") from None
    if servo not in bus.servos:
        raise DrillError(f"no servo {servo} on this bus (ids {sorted(bus.servos)})")
    return servo


def _count(text: str, verb: str) -> int:
    return int(_number(text, verb, int, 0, 1_000_000, "a whole count of replies in 0..1000000"))


def _seconds(text: str, verb: str) -> float:
    return _number(text, verb, float, 0.0, 10.0, "seconds in 0..10")


def _number(text: str, verb: str, kind: type, lo: float, hi: float, what: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not lo <= value <= hi:
        raise DrillError(f"'{verb}' needs {what}, got '{text}'")
    return value


def _error_bits(text: str, verb: str) -> int:
    bits = 0
    for name in text.split(","):
        if name not in ERRORS:
            raise DrillError(f"unknown hardware error '{name}'; one of: {', '.join(ERRORS)}")
        bits |= 1 << ERRORS[name]
    return bits
