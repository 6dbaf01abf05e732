"""Algorithm III, process of elimination (paper §3.3, §4.1-4.2).

Every start pose in a discrete table is a candidate; each measurement removes the ones
whose predicted relative height cannot match. Two ways of testing, as the paper has them:

* ``sweep="paper"`` (default): a cheap band test on every candidate (the centre must sit
  between 0.9 R and 3 R above the raw map point below it; on steep maps the upper bound is
  raised to the largest gap the map has, computed once, as the paper suggests), then the
  exact contact-surface test on the `exact_per_step` candidates most likely to fail it.
* ``sweep="full"``: the exact test on every candidate. With the contact surface
  precomputed it is one interpolated lookup; noise-free, one reading then pins the pose.

The tolerance comes from the sensor model's gate (tight when noise-free).

Noise-free, the paper's rule declares the last candidate standing. With noise that rule
is not honest: the truth can be eliminated by a bad reading and a wrong pose left alone
(B3: 9 wrong declarations in 20 runs). So with noise the survivors, once few, are
refined on every reading and judged like every other localizer's modes
(`convergence.judge`): the estimate is continuous, and it is declared only when the fit
supports it.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

import numpy as np

from service.bounds import Bound, Headings, Pitch
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
    wrap_angle,
)
from service.localization.localizers.convergence import ConvergenceRule, Modes, Verdict, judge
from service.localization.localizers.pose_table import pose_table
from service.localization.localizers.spread import pose_spread
from service.localization.localizers.symmetry import symmetries

CHUNK = 8192
JUDGED = 8
"""With noise, survivors are judged once at most this many remain."""


Sweep = Annotated[str, Bound("str", choices=("full", "paper"))]
ExactPerStep = Annotated[int, Bound("int", lo=0, hi=10_000)]

class Elimination:
    """Algorithm III over a discrete pose table."""

    name: ClassVar[str] = "elimination"

    def __init__(self, ctx: LocalizerContext, *, pitch: Pitch = None, headings: Headings = 11,
                 sweep: Sweep = "paper", exact_per_step: ExactPerStep = 5,
                 poses: np.ndarray | None = None) -> None:
        if sweep not in ("full", "paper"):
            raise ConfigError(f"elimination sweep must be 'full' or 'paper', got '{sweep}'")
        self.ctx = ctx
        self.sweep = sweep
        self.exact_per_step = exact_per_step
        table = poses if poses is not None else pose_table(
            ctx.surface.map, pitch or ctx.step_length, headings)
        self.poses = np.asarray(table, dtype=np.float64)
        surface = ctx.surface
        self.band_max = max(3 * surface.radius,
                            float(np.max(surface.centre_heights - surface.map.heights)))
        self.alive = np.ones(len(self.poses), dtype=bool)
        self.sse = np.zeros(len(self.poses))
        self.z0 = np.zeros(len(self.poses))
        self._pending: Measurement | None = None
        self._todo = np.empty(0, dtype=np.intp)
        self._cursor = 0
        self._suspicion = np.full(len(self.poses), -np.inf)
        self.noisy = float(ctx.sensor.sigma) > 1e-6
        self.rule = ConvergenceRule.for_map(ctx.surface.map.extent, ctx.step_length)
        self.motions = symmetries(ctx.surface) if self.noisy else np.empty((0, 3))
        self.history = np.zeros((1, READING_COLUMNS))
        self.verdict = Verdict(None, np.empty((0, 3)), 0.0, None, 0.0, False)

    # -- updates ---------------------------------------------------------------------------
    def start(self, first: Measurement) -> None:
        """Reference heights at each candidate start; candidates off the map are dropped."""
        z0, inside = self.ctx.surface.lookup(self.poses[:, 0], self.poses[:, 1])
        self.z0 = z0
        self.alive &= inside
        self.history = np.zeros((1, READING_COLUMNS))

    def begin_update(self, measurement: Measurement) -> None:
        self._pending = measurement
        self._todo = np.flatnonzero(self.alive)
        self._cursor = 0
        self._suspicion = np.full(len(self.poses), -np.inf)

    def background(self, budget: Budget) -> bool:
        return True  # no global check waits between updates

    def work(self, budget: Budget) -> bool:
        m = self._pending
        if m is None:
            return True
        allowance = budget.max_items
        while self._cursor < len(self._todo):
            take = CHUNK if allowance is None else min(CHUNK, allowance)
            stop = self._cursor + take
            self._test(self._todo[self._cursor:stop], m)
            self._cursor = min(stop, len(self._todo))
            if allowance is not None:
                allowance -= take
            if budget.expired() or allowance == 0:
                break
        if self._cursor >= len(self._todo):
            if self.sweep == "paper":
                self._exact_tests_on_most_suspicious(m)
            self._pending = None
            self.history = np.vstack([self.history, reading_row(m, self.ctx.walls)])
            if self.noisy:
                self.verdict = self._judge()
            return True
        return False

    def _test(self, idx: np.ndarray, m: Measurement) -> None:
        poses = self.poses[idx]
        x, y = self.ctx.motion.positions(poses, m.displacement[:2])
        surface = self.ctx.surface
        margin = 5 * self.ctx.motion.position_sigma
        ok = surface.map.inside(x, y, margin)
        if self.ctx.walls and m.blocked:  # the map's edge stopped the step: its target is off
            tx, ty = self.ctx.motion.positions(poses, np.asarray(m.displacement[:2])
                                               + np.asarray(m.command))
            slack = margin + kernels.EDGE_STEP_SLACK * float(np.hypot(*m.command))
            ok &= ~surface.map.inside(tx, ty, -slack)
        if self.sweep == "full":
            ok &= self._exact_test(idx, x, y, m)
        else:
            ok &= self._band_test(idx, x, y, m)
        self.alive[idx[~ok]] = False

    def _band_test(self, idx: np.ndarray, x: np.ndarray, y: np.ndarray, m: Measurement
                   ) -> np.ndarray:
        """The paper's cheap sweep; also ranks survivors by how likely they fail the exact one."""
        r = self.ctx.surface.radius
        tol = self.ctx.sensor.tolerance
        raw, _ = self.ctx.surface.map.lookup(x, y)
        gap = self.z0[idx] + m.displacement[2] - raw
        ok = (gap >= 0.9 * r - tol) & (gap <= self.band_max + tol)
        self._suspicion[idx] = np.where(ok, np.abs(gap - r), -np.inf)
        return ok

    def _exact_tests_on_most_suspicious(self, m: Measurement) -> None:
        """The paper's second sweep: the exact test on a bounded few, once per update."""
        live = np.flatnonzero(self.alive & np.isfinite(self._suspicion))
        k = min(self.exact_per_step, live.size)
        if k == 0:
            return
        few = live[np.argpartition(-self._suspicion[live], k - 1)[:k]]
        x, y = self.ctx.motion.positions(self.poses[few], m.displacement[:2])
        self.alive[few[~self._exact_test(few, x, y, m)]] = False

    def _exact_test(self, idx: np.ndarray, x: np.ndarray, y: np.ndarray, m: Measurement
                    ) -> np.ndarray:
        """The contact-surface test: whether each candidate predicts the reading, within
        the sensor's tolerance; the squared residuals rank the survivors."""
        predicted, _ = self.ctx.surface.lookup(x, y)
        residual = predicted - self.z0[idx] - m.displacement[2]
        self.sse[idx] += residual**2
        return self.ctx.sensor.consistent(residual)

    def _judge(self) -> Verdict:
        """With noise: the few survivors refined on every reading and judged."""
        idx = np.flatnonzero(self.alive)
        previous = self.verdict.fit.pose if self.verdict.fit is not None else None
        if idx.size == 0 or idx.size > JUDGED:
            return Verdict(None, np.empty((0, 3)), 0.0, None, 0.0, False)
        order = idx[np.argsort(self.sse[idx], kind="stable")]
        modes = Modes(centres=self.poses[order], masses=np.full(idx.size, 1.0 / idx.size),
                      labels=np.arange(idx.size))
        sensor = self.ctx.sensor
        return judge(self.ctx.surface, self.history, modes, sigma=float(sensor.sigma),
                     noisy=True, step_length=self.ctx.step_length, rule=self.rule,
                     margin=5 * self.ctx.motion.position_sigma,
                     outlier_probability=float(getattr(sensor, "outlier_probability", 0.0)),
                     outlier_range=float(getattr(sensor, "outlier_range_m", 1.0)),
                     position_sigma=self.ctx.motion.position_sigma, previous=previous,
                     motions=self.motions, polish=6)

    # -- belief ----------------------------------------------------------------------------
    def estimate(self) -> Estimate:
        idx = np.flatnonzero(self.alive)
        if idx.size == 0:
            return Estimate(pose=None, candidates=0, converged=False)
        v = self.verdict
        if self.noisy and v.fit is not None:  # the refined survivor, judged
            return Estimate(pose=v.fit.pose, candidates=int(idx.size), converged=v.converged,
                            position_sd=v.fit.position_sd, heading_sd=v.fit.heading_sd,
                            mode_mass=v.mode_mass, runner_up=v.runner_up,
                            runner_up_mass=v.runner_up_mass, information=v.fit.information)
        order = idx[np.argsort(self.sse[idx], kind="stable")]
        best = tuple(float(v) for v in self.poses[order[0]])
        runner = tuple(float(v) for v in self.poses[order[1]]) if idx.size > 1 else None
        pos_sd, head_sd = pose_spread(self.poses[idx])
        return Estimate(pose=best, candidates=int(idx.size),
                        converged=idx.size == 1 and not self.noisy,  # the paper's rule
                        position_sd=pos_sd, heading_sd=head_sd, mode_mass=1.0 / idx.size,
                        runner_up=runner, runner_up_mass=1.0 / idx.size if runner else 0.0)

    def retains(self, pose: tuple[float, float, float], position_tol: float,
                heading_tol: float) -> bool | None:
        """Whether `pose` is a live table entry; None if it is not in the table at all."""
        d_pos = np.hypot(self.poses[:, 0] - pose[0], self.poses[:, 1] - pose[1])
        d_head = np.abs(wrap_angle(self.poses[:, 2] - pose[2]))
        match = (d_pos <= position_tol) & (d_head <= heading_tol)
        if not match.any():
            return None
        return bool(self.alive[match].any())

    def hypotheses(self, limit: int | None = None) -> Hypotheses:
        idx = np.flatnonzero(self.alive)
        if limit is not None and idx.size > limit:
            idx = idx[np.argsort(self.sse[idx], kind="stable")[:limit]]
        weights = np.full(idx.size, 1.0 / max(idx.size, 1))
        return Hypotheses(poses=self.poses[idx], weights=weights)

