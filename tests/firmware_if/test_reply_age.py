"""A reply's age from the servo's clock: a late answer to an earlier read is told from its own."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_if.reply_age import FORGET_S, TICK_WRAP, ReplyAges

MS = 1_000_000  # ns


def tick_at(servo_ms: float) -> int:
    return int(servo_ms) % TICK_WRAP


@settings(max_examples=200, deadline=None)
@given(offset_ms=st.integers(0, TICK_WRAP - 1), jitter=st.lists(st.floats(0.0, 1.5),
                                                                  min_size=5, max_size=60),
       period_ms=st.floats(5.0, 40.0), rate=st.floats(0.99, 1.01))
def test_a_servo_answering_its_own_reads_is_never_stale(offset_ms, jitter, period_ms, rate):
    """Any offset between the clocks, the tick's wrap, a servo clock 1 % fast or slow, and up
    to 1.5 ms between the ask and the servo's answer."""
    ages = ReplyAges(stale_ms=5.0)
    host = 1_000.0
    for delay in jitter:
        servo = offset_ms + rate * (host - 1_000.0) + delay
        assert ages.age_ms(1, tick_at(servo), int(host * MS)) <= 5.0
        host += period_ms


@settings(max_examples=200, deadline=None)
@given(offset_ms=st.integers(0, TICK_WRAP - 1), fresh=st.integers(1, 20),
       period_ms=st.floats(8.0, 40.0), late_by=st.floats(1.0, 3.0))
def test_a_reply_to_the_read_before_is_stale(offset_ms, fresh, period_ms, late_by):
    """After `fresh` good cycles, the servo's replies fall a cycle behind: each read takes
    the answer the servo made for the one before (`late_by` periods ago at most)."""
    ages = ReplyAges(stale_ms=period_ms / 2)
    host = 50_000.0
    for _ in range(fresh):
        ages.age_ms(7, tick_at(offset_ms + host), int(host * MS))
        host += period_ms
    for _ in range(3):  # it stays stale: a stale reply never becomes the anchor
        made = host - late_by * period_ms
        assert ages.age_ms(7, tick_at(offset_ms + made), int(host * MS)) > period_ms / 2
        host += period_ms


def test_a_servo_whose_clock_restarted_is_anchored_again():
    ages = ReplyAges(stale_ms=5.0)
    ages.anchor(3, 20_000, 100 * MS)
    # rebooted: its clock reads 12 ms, 30 ms of ours later - no late reply is 20 s late
    assert ages.age_ms(3, 12, 130 * MS) == 0.0
    assert ages.age_ms(3, 22, 140 * MS) == 0.0  # judged by the new anchor
    assert ages.age_ms(3, 22, 150 * MS) > 5.0  # a reply made 10 ms before it was asked


def test_each_servo_keeps_its_own_clock_and_an_old_anchor_is_taken_afresh():
    ages = ReplyAges(stale_ms=5.0)
    ages.anchor(1, 100, 0)
    ages.anchor(2, 5_000, 0)
    assert ages.age_ms(1, 110, 10 * MS) == 0.0 and ages.age_ms(2, 5_010, 10 * MS) == 0.0
    assert ages.age_ms(1, 110, 20 * MS) > 5.0  # the same reply again, 10 ms on
    later = int((10 + FORGET_S * 1e3 + 1) * MS)  # an idle bus: the wrap makes any age possible
    assert ages.age_ms(1, 9_999, later) == 0.0
    ages.forget()
    assert ages.age_ms(2, 0, later + 10 * MS) == 0.0  # no anchor: this reply is one
