"""The fixed-rate loop on a fake clock: absolute deadlines, overruns, skip and catch-up."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.daemon.loop import RateLoop, Samples, Tick
from service.errors import ConfigError

MS = 1_000_000


class FakeTime:
    """A clock that moves only when the loop waits or a tick 'works'."""

    def __init__(self) -> None:
        self.now = 1000 * MS
        self.waits: list[int] = []

    def clock(self) -> int:
        return self.now

    def wait(self, until: int) -> None:
        self.waits.append(until)
        self.now = max(self.now, until)


def make(work_ms: list[float], overrun: str = "skip") -> tuple[RateLoop, FakeTime, list[Tick]]:
    t = FakeTime()
    ticks: list[Tick] = []

    def tick(info: Tick) -> None:
        ticks.append(info)
        t.now += int(work_ms[len(ticks) - 1] * MS)

    return RateLoop(5 * MS, tick, overrun=overrun, clock=t.clock, wait=t.wait), t, ticks


def test_deadlines_are_absolute_so_jitter_does_not_accumulate() -> None:
    loop, t, ticks = make([1.3] * 100)
    for _ in range(100):
        loop.run_once()
    due = [k.due_ns - ticks[0].due_ns for k in ticks]
    assert due == [5 * MS * i for i in range(100)]
    assert loop.overruns == 0 and loop.skipped == 0
    s = loop.summary()
    assert s["period_p50_ms"] == pytest.approx(5.0) and s["work_max_ms"] == pytest.approx(1.3)


@pytest.mark.parametrize("rate_hz", [900.0, 333.33, 200.0, 2000.0])
def test_the_rate_reads_as_configured(rate_hz: float) -> None:
    """`timing.rate_hz` read 900.000090000009 for 900 (the period is whole nanoseconds)."""
    loop = RateLoop(int(round(1e9 / rate_hz)), lambda tick: None)
    assert loop.summary()["rate_hz"] == rate_hz


def test_skip_policy_counts_overruns_and_resumes_on_the_grid() -> None:
    loop, t, ticks = make([1, 12, 1, 1])  # tick 1 overruns by 2.4 periods
    for _ in range(4):
        loop.run_once()
    assert loop.overruns == 1
    assert loop.skipped == 2
    offsets = [(k.due_ns - ticks[0].due_ns) // MS for k in ticks]
    assert offsets == [0, 5, 20, 25]
    assert all(k.start_ns >= k.due_ns for k in ticks)


def test_catch_up_runs_late_ticks_at_once() -> None:
    loop, t, ticks = make([1, 12, 1, 1, 1], overrun="catch_up")
    for _ in range(5):
        loop.run_once()
    offsets = [(k.due_ns - ticks[0].due_ns) // MS for k in ticks]
    assert offsets == [0, 5, 10, 15, 20]
    assert loop.skipped == 0 and loop.overruns == 2  # still behind after the late tick
    assert ticks[2].start_ns > ticks[2].due_ns  # ran late, immediately


def test_reset_and_retime() -> None:
    loop, t, ticks = make([1] * 10)
    for _ in range(3):
        loop.run_once()
    loop.reset_stats()
    assert loop.summary()["ticks"] == 0
    loop.retime(10 * MS)
    for _ in range(3):
        loop.run_once()
    assert ticks[-1].due_ns - ticks[-2].due_ns == 10 * MS
    with pytest.raises(ConfigError):
        loop.retime(0)
    with pytest.raises(ConfigError):
        RateLoop(MS, lambda k: None, overrun="later")


def test_samples_ring_buffer_percentiles() -> None:
    s = Samples(capacity=8)
    for v in range(1, 21):
        s.add(v * MS)
    assert s.count == 20 and s.max_ns == 20 * MS
    np.testing.assert_array_equal(s.recent(), np.arange(13, 21) * MS)
    assert s.summary_ms(window=4)["max"] == 20.0
    assert s.summary_ms(window=4)["p50"] == pytest.approx(18.5)
    s.reset()
    assert s.summary_ms() == {"p50": 0.0, "p99": 0.0, "max": 0.0}


@given(st.lists(st.integers(min_value=1, max_value=10**10), min_size=1, max_size=3000),
       st.integers(min_value=1, max_value=64))
@settings(max_examples=60, deadline=None)
def test_whole_run_percentiles_are_within_a_bin_of_exact(values: list[int],
                                                         capacity: int) -> None:
    """Over the whole run, however small the ring: at or above the exact percentile (the
    lower rank's, as a histogram reads it) and at most one bin (1 %) above it."""
    s = Samples(capacity=capacity)
    for v in values:
        s.add(v)
    got = s.summary_ms()
    data = np.sort(np.asarray(values))
    for q, key in ((0.5, "p50"), (0.99, "p99")):
        exact = data[max(0, int(np.ceil(q * len(data))) - 1)] / 1e6
        assert exact * (1 - 1e-9) <= got[key] <= max(exact * Samples.BIN_RATIO, 1e-3) + 1e-12
    assert got["max"] == data[-1] / 1e6
