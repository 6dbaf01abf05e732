"""A reply's age from the servo's clock: a late answer to an earlier read is told from its own."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_if.reply_age import FORGET_S, STALE_MS, TICK_WRAP, ReplyAges

MS = 1_000_000  # ns


def tick_at(servo_ms: float) -> int:
    return int(servo_ms) % TICK_WRAP


@settings(max_examples=300, deadline=None)
@given(offset_ms=st.integers(0, TICK_WRAP - 1), rate=st.floats(0.99, 1.01),
       period_ms=st.floats(5.0, 40.0),
       exchanges=st.lists(st.tuples(st.floats(0.0, 8.0), st.floats(0.0, 8.0)),
                          min_size=2, max_size=60))
def test_a_servo_answering_its_own_reads_is_never_stale(offset_ms, rate, period_ms,
                                                        exchanges):
    """Any offset between the clocks, the tick's wrap, a servo clock 1 % fast or slow, up to
    8 ms from the ask to the servo's answer (a slow servo, a loaded emulator) and 8 ms more
    before the host takes it in (a slow adapter, a loaded host): never older than its ask."""
    ages = ReplyAges()
    host = 1_000.0
    for answer_ms, take_ms in exchanges:
        made = host + answer_ms
        servo = offset_ms + rate * made
        age = ages.age_ms(1, tick_at(servo), int(host * MS), int((made + take_ms) * MS))
        assert age <= 1.0 + 0.01 * answer_ms  # the tick's millisecond and the clock's rate
        host += period_ms


@settings(max_examples=300, deadline=None)
@given(offset_ms=st.integers(0, TICK_WRAP - 1), fresh=st.integers(1, 20),
       period_ms=st.floats(4.0, 40.0), late_by=st.floats(1.0, 1.9))
def test_a_reply_to_the_read_before_is_stale(offset_ms, fresh, period_ms, late_by):
    """After `fresh` prompt cycles the servo's replies fall behind by `late_by` periods:
    each read takes in the answer the servo made for the read before."""
    ages = ReplyAges()
    host = 50_000.0
    for _ in range(fresh):
        ages.age_ms(7, tick_at(offset_ms + host + 0.3), int(host * MS), int((host + 0.5) * MS))
        host += period_ms
    for _ in range(3):  # it stays stale
        made = host - period_ms + 0.3  # for the read before, taken in late
        taken = made + late_by * period_ms
        assert ages.age_ms(7, tick_at(offset_ms + made), int(host * MS),
                           int(taken * MS)) > STALE_MS
        host += period_ms


def test_a_servo_whose_clock_restarted_is_dated_afresh():
    ages = ReplyAges()
    ages.age_ms(3, 20_000, 99 * MS, 100 * MS)
    # rebooted: its clock reads 12 ms, 30 ms of ours later - no late reply is 20 s late
    assert ages.age_ms(3, 12, 129 * MS, 130 * MS) == 0.0
    assert ages.age_ms(3, 22, 139 * MS, 140 * MS) == 0.0  # judged from the new floor
    assert ages.age_ms(3, 22, 149 * MS, 150 * MS) > STALE_MS  # that reply again, 10 ms on


def test_each_servo_keeps_its_own_clock_and_an_old_floor_is_set_afresh():
    ages = ReplyAges()
    ages.age_ms(1, 100, 0, 1 * MS)
    ages.age_ms(2, 5_000, 0, 1 * MS)
    assert ages.age_ms(1, 110, 10 * MS, 11 * MS) == 0.0
    assert ages.age_ms(2, 5_010, 10 * MS, 11 * MS) == 0.0
    assert ages.age_ms(1, 110, 20 * MS, 21 * MS) > STALE_MS  # servo 1's reply again, 10 ms on
    later = int((21 + FORGET_S * 1e3 + 1) * MS)  # an idle bus: the wrap makes any age possible
    assert ages.age_ms(1, 9_999, later, later) == 0.0
    ages.forget()
    assert ages.age_ms(2, 0, later + 10 * MS, later + 11 * MS) == 0.0  # dated from here on
