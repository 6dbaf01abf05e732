"""How old a servo's reply is: a late answer to an earlier read, taken for this one's.

Status packets carry no sequence number. A reply that misses its own cycle's window lands in
the next one's and reads as that cycle's answer, a cycle old: with a servo (or a USB
adapter's latency timer) a cycle late, 10 ms at 100 Hz, the bus read cycle-old positions
about 25 cycles running before two timeouts met and the fault latched (failures count only
in a row; a fault campaign saw one never latch). Each reply carries the servo's Realtime
Tick (milliseconds, wrapping at 32768), which dates it on the servo's clock; what that
clock reads against ours is bounded below by every reply, stale or not, since none is made
after it arrives: its tick minus our clock on arrival (the floor). A reply whose tick puts
it, by that floor, before its read was asked was made for an earlier read. A host or a
servo slow to answer only makes replies look younger, never older: a loaded machine cannot
fail a cycle this way (the servo's clock drifting against ours aside, allowed for).
"""

from __future__ import annotations

TICK_WRAP = 32768
"""Realtime Tick counts milliseconds from 0 to 32767, then starts again."""
STALE_MS = 2.0
"""Age from which a reply was surely made for an earlier read: its own is dated at most
the tick's millisecond before its read began (the floor only ever makes a reply look
younger), so twice that. A fixed bar, not a share of the cycle: a loop faster than its
read's wait took a reply 6 ms late, a cycle old at 200 Hz, as fresh for seconds on end
when the bar was half the budget (5 ms), a held-out campaign's finding."""
DRIFT = 0.02
"""Share of the time since the floor was set by which a servo's clock may have fallen behind
ours: the floor gives way that fast. Generous (a crystal keeps 50 ppm): a late reply is a
whole cycle old, and every reply that comes promptly sets the floor again."""
FORGET_S = 5.0
"""A floor older than this is set afresh, not judged by: past 16 s the tick's wrap makes
any age possible (a bus left idle)."""
IMPOSSIBLE_MS = 1000.0
"""An age beyond this is no late reply (the diagnosis calls a servo that late silent): the
servo's clock restarted (a brown-out, a reboot), and the reply sets its floor afresh."""


def _wrapped(ms: float) -> float:
    """`ms` brought into [-16384, 16384): a difference of two ticks."""
    return (ms + TICK_WRAP / 2) % TICK_WRAP - TICK_WRAP / 2


class ReplyAges:
    """Each servo's clock against the host's: the least it can read, from every reply."""

    def __init__(self) -> None:
        self._floors: dict[int, tuple[float, float]] = {}
        """Servo id -> (the least its tick minus our clock can be, in ms; our clock when it
        was set)."""

    def forget(self) -> None:
        """Drop every floor: the servos or the port were restarted."""
        self._floors.clear()

    def age_ms(self, servo_id: int, tick: int, asked_ns: int, received_ns: int) -> float:
        """The least time by which the servo made this reply before its read was asked (ms,
        0 if it may have been made after): at most the tick's millisecond for the read's own
        reply, about a cycle for a late reply to the read before (over `STALE_MS`: stale).
        `asked_ns` is our clock (monotonic) as the read began to go out, `received_ns` once
        its reply was in. The reply raises the servo's floor."""
        asked, received = asked_ns / 1e6, received_ns / 1e6
        arrived = tick - received  # the servo's clock, less ours, is at least this
        floor = self._floors.get(servo_id)
        if floor is None or received - floor[1] > FORGET_S * 1e3:
            self._floors[servo_id] = (arrived, received)
            return 0.0
        least = floor[0] - DRIFT * max(received - floor[1], 0.0)  # a slow servo clock
        age = _wrapped(least - (tick - asked))
        if age > IMPOSSIBLE_MS:  # a restarted clock
            self._floors[servo_id] = (arrived, received)
            return 0.0
        self._floors[servo_id] = (arrived if _wrapped(arrived - least) > 0 else least,
                                  received)
        return max(age, 0.0)
