"""Pool mechanics for sampled localizers: systematic resampling, niching, anytime jobs."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np

from service.localization import kernels
from service.localization.localizers.base import Budget


def systematic_resample(weights: np.ndarray, count: int, rng: np.random.Generator
                        ) -> np.ndarray:
    """`count` indexes drawn in proportion to `weights` with one random offset: O(N)."""
    cumulative = np.cumsum(weights)
    cumulative /= cumulative[-1]
    cumulative[-1] = 1.0
    points = (rng.random() + np.arange(count)) / count
    return np.searchsorted(cumulative, points, side="right").clip(0, len(weights) - 1)


def thin(weights: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indexes of `count` distinct members, each kept with probability
    min(1, c w_i) (systematic sampling proportional to size, O(N) after a short search for
    c): strong members always stay, weak ones survive in proportion to their weight, so a
    cut never silently removes every member near a true pose that merely fits a little
    worse for now."""
    n = len(weights)
    if count >= n:
        return np.arange(n)
    if count <= 0:  # the solve below has no j < count: it would keep nearly every member
        return np.empty(0, dtype=np.int64)
    w = np.maximum(weights, 0.0) + 1e-300
    # c solves sum(min(1, c w)) = count: the j heaviest are kept surely, the rest share
    # count - j in proportion to weight; the right j is the first where that is consistent.
    desc = np.sort(w)[::-1]
    tail = np.cumsum(desc[::-1])[::-1]  # sum of desc[j:]
    j = np.arange(n)
    c = (count - j) / tail
    ok = (c * desc <= 1.0) & (j < count)
    c = float(c[int(np.argmax(ok))]) if ok.any() else 1.0 / desc[count - 1]
    pi = np.minimum(1.0, c * w)
    cumulative = np.cumsum(pi)
    points = rng.random() + np.arange(int(np.floor(cumulative[-1] + 1e-9)))
    return np.unique(np.searchsorted(cumulative, points, side="right").clip(0, n - 1))


def effective_sample_size(weights: np.ndarray) -> float:
    """1 / sum(w^2) of normalized weights: how many members really carry the belief."""
    total = weights.sum()
    if total <= 0:
        return 0.0
    w = weights / total
    return float(1.0 / np.sum(w * w))


def niche(poses: np.ndarray, score: np.ndarray, position_cell: float, heading_cell: float,
          limit: int | None = None, *, ordered: bool = True) -> np.ndarray:
    """Indexes of the best-scoring member in each (position, heading) cell.

    Keeping one member per cell stops one mode's offspring from crowding every other mode
    out of a bounded pool: modes die from evidence, not from sampling drift. Best first
    (the `limit` best, if given); with `ordered=False`, in pool order, which spares a sort
    of what may be the whole pool.
    """
    span = 1 << 20
    kx = np.floor(poses[:, 0] / position_cell).astype(np.int64) % span
    ky = np.floor(poses[:, 1] / position_cell).astype(np.int64) % span
    kh = np.floor((poses[:, 2] % (2 * np.pi)) / heading_cell).astype(np.int64)
    keys = (kx * span + ky) * 4096 + kh
    best = np.flatnonzero(kernels.best_per_key(keys, np.ascontiguousarray(score,
                                                                          dtype=np.float64)))
    if not ordered:
        return best
    if limit is not None and limit < len(best):
        best = best[np.argpartition(-score[best], limit - 1)[:limit]]
    return best[np.argsort(-score[best], kind="stable")]


class AnytimeJob:
    """Runs an update written as a generator that yields between bounded slices of work.

    The generator asks `take(n)` how many hypotheses its next slice may process and yields
    the count it processed; `work` stops once the budget's items or time are used up. The
    slicing never changes the result, only how many `work` calls it takes.
    """

    def __init__(self, make: Callable[[AnytimeJob], Iterator[int]]) -> None:
        self._allowance: int | None = None
        self._expected_ns = 0
        self._steps = make(self)
        self.done = False

    def expect(self, duration_ns: int) -> None:
        """Called by the generator before a yield: its next slice will take about this
        long (work it cannot split, such as a judgement), so `work` starts it only when
        that fits what is left of the budget."""
        self._expected_ns = duration_ns

    def take(self, default: int) -> int:
        """Size of the next slice: `default`, or less when the call's budget is smaller."""
        return default if self._allowance is None else max(1, min(default, self._allowance))

    def work(self, budget: Budget) -> bool:
        """Run slices until done or the budget is spent. A slice is started only if it
        would end by the deadline, judged by the last slice's length (or the generator's
        `expect`), so a call overshoots by a misjudgement, not by a whole slice."""
        self._allowance = budget.max_items
        while not self.done:
            started = time.monotonic_ns()
            try:
                used = next(self._steps)
            except StopIteration:
                self.done = True
                break
            if self._allowance is not None:
                self._allowance -= max(1, used)
                if self._allowance <= 0:
                    break
            expected = max(time.monotonic_ns() - started, self._expected_ns)
            self._expected_ns = 0
            if not budget.fits(expected):
                break
        return self.done
