"""How old a servo's reply is: a late answer to an earlier read, taken for this one's.

Status packets carry no sequence number. A reply that misses its own cycle's window lands in
the next one's and reads as that cycle's answer, a cycle old: with a servo (or a USB
adapter's latency timer) a cycle late, 10 ms at 100 Hz, the bus read cycle-old positions
about 25 cycles running before two timeouts met and the fault latched (failures count only
in a row; a fault campaign saw one never latch). Each reply
carries the servo's Realtime Tick (milliseconds, wrapping at 32768), so its age is judged
against when it was asked: the servo's clock must keep pace with ours from the freshest
reply it gave so far (the anchor). A patient read, whose replies are surely its own, sets
the first anchor (`DxlBus.detect_fast_read`, `DxlBus.reset`).
"""

from __future__ import annotations

TICK_WRAP = 32768
"""Realtime Tick counts milliseconds from 0 to 32767, then starts again."""
DRIFT = 0.02
"""Share of the time between replies by which a servo's clock may run slow against ours:
the anchor gives way that fast. Generous (a crystal keeps 50 ppm): a late reply is a whole
cycle old, and the anchor is taken again from every fresh reply."""
FORGET_S = 5.0
"""An anchor older than this is taken afresh, not judged by: past 16 s the tick's wrap
makes any age possible (a bus left idle)."""
IMPOSSIBLE_MS = 1000.0
"""An age beyond this is no late reply (the diagnosis calls a servo that late silent): the
servo's clock restarted (a brown-out, a reboot), and the reply anchors its clock again."""


def _wrapped(ms: float) -> float:
    """`ms` brought into [-16384, 16384): a difference of two ticks."""
    return (ms + TICK_WRAP / 2) % TICK_WRAP - TICK_WRAP / 2


class ReplyAges:
    """Each servo's clock against the host's, from the freshest reply it gave."""

    def __init__(self, stale_ms: float) -> None:
        self.stale_ms = stale_ms
        """Age from which a reply is a late answer to an earlier read, not this one's."""
        self._anchors: dict[int, tuple[float, float]] = {}
        """Servo id -> (its tick minus our clock in ms at the ask, our clock then)."""

    def forget(self) -> None:
        """Drop every anchor: the servos or the port were restarted."""
        self._anchors.clear()

    def anchor(self, servo_id: int, tick: int, asked_ns: int) -> None:
        """Take the reply to a read asked at `asked_ns` (monotonic) as surely fresh."""
        asked = asked_ns / 1e6
        self._anchors[servo_id] = (tick - asked, asked)

    def age_ms(self, servo_id: int, tick: int, asked_ns: int) -> float:
        """How long before the read asked at `asked_ns` the servo made this reply (ms):
        about 0 for the read's own reply, a cycle or more for a late reply to an earlier
        read. A reply younger than `stale_ms` dates the anchor anew (the freshest becomes
        it); an older one leaves it. A servo with no anchor, or too old a one, is anchored
        by this reply, whose age is then 0."""
        asked = asked_ns / 1e6
        anchor = self._anchors.get(servo_id)
        if anchor is None or asked - anchor[1] > FORGET_S * 1e3:
            self.anchor(servo_id, tick, asked_ns)
            return 0.0
        lead = anchor[0] - DRIFT * max(asked - anchor[1], 0.0)  # a slow servo clock
        age = _wrapped(lead - (tick - asked))
        if age <= 0 or age > IMPOSSIBLE_MS:
            self.anchor(servo_id, tick, asked_ns)  # fresher than the anchor, or a new clock
            return 0.0
        if age <= self.stale_ms:
            self._anchors[servo_id] = (lead, asked)
        return age
