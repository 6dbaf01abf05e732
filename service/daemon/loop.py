"""A fixed-rate loop on absolute monotonic deadlines that counts its overruns.

Tick k is due at `t0 + k * period`, so timing errors never accumulate. A tick whose work
runs past the next deadline is an overrun; the policy then either skips to the next
period boundary still ahead ('skip', the default: the control rate stays on its grid and
missed ticks are counted) or runs the late ticks at once ('catch_up'). Clock and wait are
injected so tests drive the loop deterministically.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.errors import ConfigError


class Samples:
    """Durations (ns): a ring buffer for percentiles over the recent window, and a log
    histogram for the whole run (a ring alone forgot all but the last 65,536 ticks, 5.5
    minutes at 200 Hz, and a percentile over it cost `status` 1-2 ms of the loop's time)."""

    BIN_RATIO = 1.01
    """Neighbouring histogram edges differ by 1 %: whole-run percentiles are exact to 1 %."""
    _LOW_NS = 1_000
    _LOG_RATIO = math.log(BIN_RATIO)
    _BINS = int(math.log(1e11 / _LOW_NS) / _LOG_RATIO) + 2  # 1 us .. 100 s

    def __init__(self, capacity: int = 1 << 16) -> None:
        self._buf = np.zeros(capacity, dtype=np.int64)
        self._hist = np.zeros(self._BINS, dtype=np.int64)
        self._n = 0
        self.max_ns = 0

    def add(self, value_ns: int) -> None:
        self._buf[self._n % len(self._buf)] = value_ns
        self._hist[self._bin(value_ns)] += 1
        self._n += 1
        self.max_ns = max(self.max_ns, int(value_ns))

    def _bin(self, value_ns: int) -> int:
        if value_ns <= self._LOW_NS:
            return 0
        k = 1 + int(math.log(value_ns / self._LOW_NS) / self._LOG_RATIO)
        return min(k, self._BINS - 1)

    def _upper_edge_ns(self, k: int) -> float:
        return self._LOW_NS * self.BIN_RATIO ** k

    def reset(self) -> None:
        self._n = 0
        self._hist[:] = 0
        self.max_ns = 0

    @property
    def count(self) -> int:
        return self._n

    def recent(self, window: int | None = None) -> np.ndarray:
        n = min(self._n, len(self._buf))
        if window is not None:
            n = min(n, window)
        if n == 0:
            return self._buf[:0]
        end = self._n % len(self._buf)
        idx = (np.arange(end - n, end)) % len(self._buf)
        return self._buf[idx]

    def summary_ms(self, window: int | None = None) -> dict[str, float]:
        """p50, p99 and max over the last `window` samples (exact), or over the whole run
        (None: from the histogram, each percentile the upper edge of its bin, capped at
        the true maximum)."""
        if self._n == 0:
            return {"p50": 0.0, "p99": 0.0, "max": 0.0}
        if window is not None:
            data = self.recent(window)
            p50, p99 = np.percentile(data, [50, 99])
            return {"p50": float(p50) / 1e6, "p99": float(p99) / 1e6,
                    "max": float(data.max()) / 1e6}
        cumulative = np.cumsum(self._hist)
        p50, p99 = (min(self._upper_edge_ns(int(np.searchsorted(cumulative, q * self._n))),
                        self.max_ns) for q in (0.5, 0.99))
        return {"p50": p50 / 1e6, "p99": p99 / 1e6, "max": self.max_ns / 1e6}


@dataclass(frozen=True)
class Tick:
    index: int
    start_ns: int
    """When the tick actually started."""
    due_ns: int
    """When it was due."""
    deadline_ns: int
    """When the next tick is due: the work of this tick should end before."""


def sleep_until(clock: Callable[[], int]) -> Callable[[int], None]:
    """A wait function that sleeps on `clock` until a deadline."""

    def wait(until_ns: int) -> None:
        while True:
            left = until_ns - clock()
            if left <= 0:
                return
            time.sleep(left / 1e9)

    return wait


class RateLoop:
    """Call `tick(Tick)` every `period_ns` on absolute deadlines; keep timing statistics."""

    def __init__(self, period_ns: int, tick: Callable[[Tick], None], *, overrun: str = "skip",
                 clock: Callable[[], int] = time.monotonic_ns,
                 wait: Callable[[int], None] | None = None) -> None:
        if period_ns <= 0:
            raise ConfigError("loop period must be > 0")
        if overrun not in ("skip", "catch_up"):
            raise ConfigError("overrun policy must be 'skip' or 'catch_up'")
        self.period_ns = period_ns
        self.overrun = overrun
        self._tick = tick
        self._clock = clock
        self._wait = wait or sleep_until(clock)
        self.period = Samples()
        self.work = Samples()
        self.ticks = 0
        self.overruns = 0
        self.skipped = 0
        """Periods left out by the 'skip' policy."""
        self._t0: int | None = None
        self._k = 0
        self._last_start: int | None = None

    def reset_stats(self) -> None:
        self.period.reset()
        self.work.reset()
        self.overruns = self.skipped = 0
        self.ticks = 0
        self._last_start = None

    def retime(self, period_ns: int) -> None:
        """Change the rate: the deadline grid restarts at the next tick."""
        if period_ns <= 0:
            raise ConfigError("loop period must be > 0")
        self.period_ns = period_ns
        self._t0 = None
        self._k = 0
        self._last_start = None

    def run_once(self) -> None:
        """Wait for the next due time, run one tick, apply the overrun policy."""
        if self._t0 is None:
            self._t0 = self._clock()
        due = self._t0 + self._k * self.period_ns
        self._wait(due)
        start = self._clock()
        if self._last_start is not None:
            self.period.add(start - self._last_start)
        self._last_start = start
        next_due = due + self.period_ns
        self._tick(Tick(index=self.ticks, start_ns=start, due_ns=due, deadline_ns=next_due))
        end = self._clock()
        self.work.add(end - start)
        self.ticks += 1
        self._k += 1
        if end > next_due:
            self.overruns += 1
            if self.overrun == "skip":
                behind = (end - self._t0) // self.period_ns + 1  # first boundary after `end`
                self.skipped += int(behind - self._k)
                self._k = int(behind)

    def run(self, should_stop: Callable[[], bool]) -> None:
        while not should_stop():
            self.run_once()

    def summary(self, window: int | None = None) -> dict[str, float | int]:
        """Timing for the state stream (recent window) or a report (whole run)."""
        period, work = self.period.summary_ms(window), self.work.summary_ms(window)
        return {
            "rate_hz": float(f"{1e9 / self.period_ns:.6g}"),  # 900, not 900.00009 (whole ns)
            "ticks": self.ticks, "overruns": self.overruns,
            "skipped": self.skipped,
            "period_p50_ms": period["p50"], "period_p99_ms": period["p99"],
            "period_max_ms": period["max"],
            "work_p50_ms": work["p50"], "work_p99_ms": work["p99"], "work_max_ms": work["max"],
        }
