"""Algorithm I: a position probability grid (paper §3.1, Eq. 1-3), heading as an option.

A histogram over the finger's *current* position on a regular grid — and, unless
`headings=1`, over its heading in `headings` bins. Each move spreads every cell's mass to
where the move could have taken it (Eq. 2: the measured step d, with error factor ε), and
weights it by how well the height change between the two cells matches the measured one
(Eq. 3: the z offset is unknown, so only the change counts).

* With heading bins each bin shifts its mass by the step turned through its own heading,
  then a Gaussian blur of ε·d (and of a heading sd) spreads it.
* With `headings=1` (the paper's original) a cell receives mass from a ring of cells at
  distance d around it: it forgets the heading, which is the weakness the paper points
  out, and why it reports its start pose only through the pattern matching of
  Algorithm II (`match.py`), which builds on this class.

The loops run over headings or ring directions (tens), each vectorized over all cells.
Once the mass concentrates, the start pose of the leading cells is polished and refined
by least squares and declared only when `convergence.py` agrees.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Annotated, ClassVar

import numpy as np
from scipy import ndimage

from service.bounds import Bound, Count, Headings, Pitch, Share
from service.errors import ConfigError
from service.localization import kernels
from service.localization.localizers.base import (
    READING_COLUMNS,
    Budget,
    Estimate,
    Hypotheses,
    LocalizerContext,
    Measurement,
    reading_row,
)
from service.localization.localizers.convergence import (
    ConvergenceRule,
    Verdict,
    group_modes,
    judge,
)
from service.localization.localizers.fitting import sample, typical_slope
from service.localization.localizers.heading_scan import best_headings
from service.localization.localizers.pool import AnytimeJob
from service.localization.localizers.spread import pose_spread
from service.localization.localizers.symmetry import symmetries
from service.localization.localizers.turned import Weighing
from service.localization.localizers.whole_map import WholeMapCheck
from service.localization.models import rotate

RING = 32
"""Directions of the ring a position-only grid spreads each step over."""
EDGE_MISS = 1e-6
"""Share of its mass a cell keeps when a blocked step says its pose cannot be the truth:
a trace, not nothing, so a mistaken wall cannot erase the truth for good."""


HeadingSd = Annotated[float, Bound("float", lo=0.01, hi=180.0)]
"""Degrees of heading noise a step is assumed to add."""

PROFILE_REFUSAL = "the grid localizers need a 2-D map; use particles for a profile"


class Grid:
    """Algorithm I over (position[, heading]) cells of the current finger position."""

    name: ClassVar[str] = "grid"
    profiles: ClassVar[str | None] = PROFILE_REFUSAL
    """Why this localizer refuses a profile (None: it takes one); read before it is built
    (`scenario.check_algorithm`)."""

    def __init__(self, ctx: LocalizerContext, *, cell: Pitch = None, headings: Headings = 36,
                 epsilon: Share = 0.1, heading_sd_deg: HeadingSd = 2.0, keep: Count = 3000,
                 rivals: Count = 8, rule: ConvergenceRule | None = None) -> None:
        if headings < 1:
            raise ConfigError(f"grid headings must be >= 1, got {headings}")
        if ctx.surface.map.is_profile:
            raise ConfigError(PROFILE_REFUSAL)
        kernels.warm_up()  # compile before the first update, not during it
        self.ctx = ctx
        self.cell = float(cell or 0.5 * ctx.step_length)
        if not self.cell > 0:
            raise ConfigError(f"grid cell must be > 0 metres, got {self.cell}")
        self.headings = headings
        self.epsilon, self.heading_sd = epsilon, np.deg2rad(heading_sd_deg)
        self.keep, self.rivals = keep, rivals
        self.rule = rule or ConvergenceRule.for_map(ctx.surface.map.extent, ctx.step_length)
        x_max, y_max = ctx.surface.map.extent
        self.xs = np.arange(0.0, x_max + 1e-12, self.cell)
        self.ys = np.arange(0.0, y_max + 1e-12, self.cell)
        self.angles = np.arange(headings) * (2 * np.pi / headings)
        self.gx, self.gy = np.meshgrid(self.xs, self.ys)
        self.c_here = sample(ctx.surface, self.gx, self.gy)[0]
        self.sigma = float(ctx.sensor.sigma)
        self.noisy = self.sigma > 1e-6
        # two cells' quantization and a slope make the height change uncertain
        self.slope = typical_slope(ctx.surface)
        self.grid_sigma = float(np.hypot(2 * self.sigma, self.slope * 0.5 * self.cell))
        self.outlier_p = float(getattr(ctx.sensor, "outlier_probability", 0.0))
        self.outlier_range = float(getattr(ctx.sensor, "outlier_range_m", 1.0))
        self.margin = 5 * ctx.motion.position_sigma
        self.prob = np.zeros((headings, *self.gx.shape))
        self.history = np.zeros((1, READING_COLUMNS))
        self.verdict = Verdict(None, np.empty((0, 3)), 0.0, None, 0.0, False)
        step = ctx.step_length
        self.whole_map = WholeMapCheck(Weighing(
            ctx.surface, self.sigma, max(self.sigma, 0.002 * step), ctx.motion.position_sigma,
            self.margin, self.outlier_p, self.outlier_range, step,
            (0.25 * step, float(np.deg2rad(5.0))), self.rule.mode_mass))
        """What a declaration waits on: the certificate of the whole map (`whole_map`)."""
        self.motions = symmetries(ctx.surface)  # found once, not inside an update's slice
        self._job: AnytimeJob | None = None
        self._judge_ns = 0
        """How long the last judgement took: a hint for slicing, never for results."""

    # -- updates ---------------------------------------------------------------------------
    def start(self, first: Measurement) -> None:
        self.history = np.zeros((1, READING_COLUMNS))
        self.prob[:] = 1.0 / self.prob.size

    def begin_update(self, measurement: Measurement) -> None:
        self._job = AnytimeJob(lambda job: self._update(job, measurement))

    def background(self, budget: Budget) -> bool:
        """The check of the whole map a declaration waits on, between updates."""
        if not self.whole_map.pending:
            return True
        verdict = self.whole_map.work(budget, self.history)
        if verdict is None:
            return False
        self.verdict = verdict
        return True

    def work(self, budget: Budget) -> bool:
        """Sliced between heading layers (or ring directions), then the judgement."""
        return True if self._job is None else self._job.work(budget)

    def _update(self, job: AnytimeJob, m: Measurement) -> Iterator[int]:
        previous = self.history[-1]
        self.history = np.vstack([self.history, reading_row(m, self.ctx.walls)])
        step = self.history[-1] - previous
        yield from self._predict_and_weigh(step[:2], step[2])
        if self.ctx.walls and m.blocked:
            yield from self._edge(np.asarray(m.command, dtype=np.float64))
        yield from self._after_update()
        job.expect(self._judge_ns)  # the judgement is one slice: start it in a fresh call
        yield self.prob.size
        started = time.monotonic_ns()
        self.verdict = self.whole_map.hold(self._judge(), self.history)
        self._judge_ns = time.monotonic_ns() - started

    def _likelihood(self, dz_cells: np.ndarray, dz: float) -> np.ndarray:
        z = (dz_cells - dz) / self.grid_sigma
        return (1 - self.outlier_p) * np.exp(-0.5 * z * z) / self.grid_sigma + \
            self.outlier_p / self.outlier_range

    def _predict_and_weigh(self, d: np.ndarray, dz: float) -> Iterator[int]:
        """Eq. 1-3: spread each cell by the step, weight by the height change.

        Yields after each heading layer (or ring direction): one slice of anytime work.
        """
        length = float(np.hypot(*d))
        if length < 0.2 * self.cell:  # a blocked step: nothing moved, nothing to learn
            return
        new = np.zeros_like(self.prob)
        layer = self.prob[0].size
        if self.headings > 1:
            for h, angle in enumerate(self.angles):
                vx, vy = rotate(np.asarray(angle), d[0], d[1])
                new[h] = self._carry(self.prob[h], float(vx), float(vy), dz)
                yield layer
        else:
            for angle in np.arange(RING) * (2 * np.pi / RING):
                vx, vy = length * np.cos(angle), length * np.sin(angle)
                new[0] += self._carry(self.prob[0], float(vx), float(vy), dz) / RING
                yield layer
        # the spread of Eq. 2: over position layer by layer, then over heading in blocks
        # of rows, so no slice filters the whole grid at once
        spread = max(self.epsilon * length / self.cell, 0.3)
        for h in range(len(new)):
            new[h] = ndimage.gaussian_filter(new[h], sigma=spread, mode="constant")
            yield layer
        if self.headings > 1:
            heading_spread = self.heading_sd / (2 * np.pi / self.headings)
            for rows in np.array_split(np.arange(new.shape[1]), len(new)):
                new[:, rows] = ndimage.gaussian_filter1d(new[:, rows], heading_spread, axis=0,
                                                         mode="wrap")
                yield len(rows) * new.shape[2] * len(new)
        total = new.sum()
        self.prob = new / total if total > 0 else np.full_like(new, 1.0 / new.size)

    def _edge(self, command: np.ndarray) -> Iterator[int]:
        """A step the map's edge stopped: cells whose target lies well inside the map
        could not have been stopped, and keep only a trace of their mass."""
        length = float(np.hypot(*command))
        slack = self.margin + kernels.EDGE_STEP_SLACK * length
        for h, angle in enumerate(self.angles):
            if self.headings > 1:
                vx, vy = rotate(np.asarray(angle), command[0], command[1])
                inside = self.ctx.surface.map.inside(self.gx + vx, self.gy + vy, -slack)
            else:  # heading unknown: only cells no direction could take off the map
                inside = self.ctx.surface.map.inside(self.gx, self.gy, -(length + slack))
            self.prob[h][inside] *= EDGE_MISS
            yield self.prob[h].size
        total = self.prob.sum()
        if total > 0:
            self.prob /= total

    def _carry(self, layer: np.ndarray, vx: float, vy: float, dz: float) -> np.ndarray:
        """Mass arriving at each cell from the cell one step (vx, vy) back, times Eq. 3."""
        moved = ndimage.shift(layer, (vy / self.cell, vx / self.cell), order=1, mode="constant")
        before = sample(self.ctx.surface, self.gx - vx, self.gy - vy)[0]
        return moved * self._likelihood(self.c_here - before, dz)

    def _after_update(self) -> Iterator[int]:
        """Hook for Algorithm II: more anytime work after the grid's own."""
        yield from ()

    # -- hypotheses ------------------------------------------------------------------------
    def _start_poses(self, limit: int) -> tuple[np.ndarray, np.ndarray]:
        """Start poses and weights of the `limit` heaviest cells (current pose minus path)."""
        flat = self.prob.ravel()
        k = min(limit, flat.size)
        idx = np.argpartition(-flat, k - 1)[:k]
        idx = idx[np.argsort(-flat[idx], kind="stable")]
        h, r, c = np.unravel_index(idx, self.prob.shape)
        heading = self.angles[h] if self.headings > 1 else self._fit_headings(r, c)
        d = self.history[-1]
        dx, dy = rotate(heading, d[0], d[1])
        poses = np.column_stack([self.xs[c] - dx, self.ys[r] - dy, heading])
        return poses, flat[idx]

    def _fit_headings(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Position-only grid: the heading that best lays the path onto the map at each cell
        (a scan, vectorized over cells and candidate headings)."""
        return best_headings(self.ctx.surface, self.history, self.xs[cols], self.ys[rows])[0]

    def _judge(self) -> Verdict:
        poses, w = self._start_poses(self.keep)
        # modes a basin apart (a step, 20 degrees, plus a cell): nearer cells are one mode
        modes = group_modes(poses, w, self.ctx.step_length + self.cell,
                            np.deg2rad(20.0) + np.pi / max(self.headings, 1), self.rivals)
        return judge(self.ctx.surface, self.history, modes, sigma=self.sigma, noisy=self.noisy,
                     step_length=self.ctx.step_length, rule=self.rule, margin=self.margin,
                     outlier_probability=self.outlier_p, outlier_range=self.outlier_range,
                     position_sigma=self.ctx.motion.position_sigma,
                     previous=None if self.verdict.fit is None else self.verdict.fit.pose,
                     motions=self.motions, polish=6)

    # -- belief ----------------------------------------------------------------------------
    def estimate(self) -> Estimate:
        poses, w = self._start_poses(self.keep)
        v = self.verdict
        if v.fit is not None:
            pose, pos_sd, head_sd = v.fit.pose, v.fit.position_sd, v.fit.heading_sd
        else:
            pose = tuple(float(p) for p in poses[0])
            pos_sd, head_sd = pose_spread(poses, w)
        return Estimate(pose=pose, candidates=int(np.count_nonzero(self.prob > 1e-9)),
                        converged=v.converged, position_sd=pos_sd, heading_sd=head_sd,
                        mode_mass=v.mode_mass if v.fit is not None else float(w[0] / w.sum()),
                        runner_up=v.runner_up, runner_up_mass=v.runner_up_mass,
                        information=None if v.fit is None else v.fit.information,
                        pending=self.whole_map.pending, held_back=v.held_back)

    def hypotheses(self, limit: int | None = None) -> Hypotheses:
        limit = limit or self.keep
        poses, w = self._start_poses(limit)
        if self.verdict.fit is not None:  # the refined pose leads
            poses = np.vstack([[self.verdict.fit.pose], poses])[:limit]
            w = np.concatenate([[w[0]], w])[:limit]
        w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))  # every listed one drawable
        return Hypotheses(poses=poses, weights=w / w.sum())
