"""Pool mechanics for sampled localizers: systematic resampling, niching, anytime jobs."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from service.localizers.base import Budget


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


def niche(poses: np.ndarray, score: np.ndarray, position_cell: float, heading_cell: float
          ) -> np.ndarray:
    """Indexes of the best-scoring member in each (position, heading) cell, best first.

    Keeping one member per cell stops one mode's offspring from crowding every other mode
    out of a bounded pool: modes die from evidence, not from sampling drift.
    """
    order = np.argsort(-score, kind="stable")
    span = 1 << 20
    kx = np.floor(poses[order, 0] / position_cell).astype(np.int64) % span
    ky = np.floor(poses[order, 1] / position_cell).astype(np.int64) % span
    kh = np.floor((poses[order, 2] % (2 * np.pi)) / heading_cell).astype(np.int64)
    keys = (kx * span + ky) * 4096 + kh
    _, first = np.unique(keys, return_index=True)
    return order[np.sort(first)]


class AnytimeJob:
    """Runs an update written as a generator that yields between bounded slices of work.

    The generator asks `take(n)` how many hypotheses its next slice may process and yields
    the count it processed; `work` stops once the budget's items or time are used up. The
    slicing never changes the result, only how many `work` calls it takes.
    """

    def __init__(self, make: Callable[[AnytimeJob], Iterator[int]]) -> None:
        self._allowance: int | None = None
        self._steps = make(self)
        self.done = False

    def take(self, default: int) -> int:
        """Size of the next slice: `default`, or less when the call's budget is smaller."""
        return default if self._allowance is None else max(1, min(default, self._allowance))

    def work(self, budget: Budget) -> bool:
        self._allowance = budget.max_items
        while not self.done:
            try:
                used = next(self._steps)
            except StopIteration:
                self.done = True
                break
            if self._allowance is not None:
                self._allowance -= max(1, used)
                if self._allowance <= 0:
                    break
            if budget.expired():
                break
        return self.done
