"""Algorithm II: a position grid plus pattern matching of the collected readings (§3.2).

Algorithm I's position-only grid forgets the heading, so it can find the right place and
later wander off it. Here the finger also keeps every reading in its own frame; after each
update, starting at the most probable cells, it lays the collected path onto the map at
each cell, turning it through every candidate heading, polishes the best fit (rotation and
offset) and removes the cell from the grid if even that cannot fit. It stops when one
location dominates and fits (`convergence.py`).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import ClassVar

import numpy as np

from service.bounds import Count, Gate, Headings
from service.localization.localizers.base import LocalizerContext, wrap_angle
from service.localization.localizers.fitting import gauss_newton, offset_residuals
from service.localization.localizers.grid import Grid
from service.localization.localizers.heading_scan import SCAN, best_headings
from service.localization.models import rotate

SCAN_LOOKUPS = 20_000
"""Map lookups per anytime slice of the rotation scan (about a millisecond)."""


class Match(Grid):
    """Algorithm II: a position-only grid whose cells must also fit the readings' pattern."""

    name: ClassVar[str] = "match"

    def __init__(self, ctx: LocalizerContext, *, headings: Headings = 1, keep: Count = 200,
                 matched: Count = 200, gate: Gate = 4.0, **options) -> None:
        super().__init__(ctx, headings=headings, keep=keep, **options)
        self.matched = matched
        self.gate = gate
        self.dropped = 0
        self._scanned = (-1, np.full(self.gx.size, np.nan))
        """(readings, best heading per cell or NaN): the scan's results for this history,
        reused by `_fit_headings` so the judgement does not scan again."""

    def _fit_headings(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The rotation scan's heading per cell, scanning only cells not yet scanned for
        the current readings."""
        readings, known = self._scanned
        if readings != len(self.history):
            known = np.full(self.gx.size, np.nan)
            self._scanned = (len(self.history), known)
        cells = np.ravel_multi_index((rows, cols), self.gx.shape)
        missing = np.isnan(known[cells])
        if missing.any():
            known[cells[missing]] = best_headings(self.ctx.surface, self.history,
                                                  self.xs[cols[missing]],
                                                  self.ys[rows[missing]])[0]
        return known[cells]

    def _after_update(self) -> Iterator[int]:
        """Pattern matching: drop the leading cells whose best rotation cannot fit.

        The rotation scan is sliced by blocks of cells for the anytime budget.
        """
        if len(self.history) < 4:
            return
        flat = self.prob.reshape(self.headings, -1)
        total = flat.sum(axis=0)
        k = min(self.matched, int(np.count_nonzero(total)))
        if k == 0:
            return
        cells = np.argpartition(-total, k - 1)[:k]
        r, c = np.unravel_index(cells, self.gx.shape)
        per_slice = max(1, SCAN_LOOKUPS // (SCAN * len(self.history)))
        for block in range(0, k, per_slice):
            part = slice(block, block + per_slice)
            self._fit_headings(r[part], c[part])
            yield len(cells[part]) * SCAN
        heading = self._fit_headings(r, c)
        d = self.history[-1]
        dx, dy = rotate(heading, d[0], d[1])
        starts = np.column_stack([self.xs[c] - dx, self.ys[r] - dy, heading])
        polished = gauss_newton(self.ctx.surface, starts, self.history,
                                np.ones(len(self.history)), iterations=3, max_move=self.cell)
        polished[:, 2] = wrap_angle(polished[:, 2])
        res, ok = offset_residuals(self.ctx.surface, polished, self.history, self.margin)
        rms = np.sqrt(np.mean(np.where(ok, res * res, 1.0), axis=1))
        tolerance = self.gate * np.hypot(self.sigma, 0.02 * self.ctx.step_length * self.slope)
        bad = cells[rms > tolerance]
        if bad.size < cells.size:  # never empty the grid on the matcher's word alone
            flat[:, bad] = 0.0
            self.dropped += int(bad.size)
            self.prob /= self.prob.sum()
