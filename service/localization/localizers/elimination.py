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
supports it. The table's survivors are not the whole map, though: noise can eliminate the
truth's entry (a pose between entries fits the readings only roughly) and leave a wrong
one that fits alone. So with noise the whole map is swept between steps as `particles.py`
sweeps it (`sweep.py`), the poses that fit best join the judged modes as rivals, and
nothing is declared before a sweep has passed over every cell. (A held-out rack profile,
one tooth short: 7 of 30 noisy runs declared the mirror image, 42-98 mm and 180 degrees
off.)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
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
from service.localization.localizers.convergence import (
    ConvergenceRule,
    Modes,
    Verdict,
    distinct,
    judge,
)
from service.localization.localizers.fitting import (
    fit_log_likelihood,
    gauss_newton,
    residuals,
)
from service.localization.localizers.pool import AnytimeJob
from service.localization.localizers.pose_table import pose_table
from service.localization.localizers.spread import pose_spread
from service.localization.localizers.sweep import Sweep as WholeMapSweep
from service.localization.localizers.symmetry import images, symmetries

CHUNK = 8192
FELT = 0.001
"""Steps by which readings must depart from a plane to have felt the surface's shape
(noise-free: 10 um on a 10 mm step; at 0.1 mm one of B1's 103 runs was held back until
it ran out of steps)."""
IMAGE_FIT = 0.01
"""Steps within which an image of the table's last pose fitting every reading fits them
as well (noise-free): the map's samples turned by a symmetry are not its own to the
micrometre, though a reading cannot tell them apart."""
JUDGED = 8
"""With noise, survivors are judged once at most this many remain."""
RIVALS = 32
"""Most poses the sweep found that the judge weighs beside the survivors, best first."""
SWEEP_STEPS = 8
"""Gauss-Newton steps a cell the sweep hands over takes onto the readings."""


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
        self.motions = symmetries(ctx.surface)
        self.history = np.zeros((1, READING_COLUMNS))
        self.verdict = Verdict(None, np.empty((0, 3)), 0.0, None, 0.0, False)
        self.margin = 5 * ctx.motion.position_sigma
        self.whole_map = WholeMapSweep(ctx.surface, ctx.step_length, float(ctx.sensor.sigma),
                               self.margin) if self.noisy else None
        """With noise, the sweep of every pose on the map a declaration waits on."""
        self.rivals = np.empty((0, 3))
        """The poses the sweep found that fit the readings best, polished onto them."""
        self._between: AnytimeJob | None = None

    # -- updates ---------------------------------------------------------------------------
    def start(self, first: Measurement) -> None:
        """Reference heights at each candidate start; candidates off the map are dropped."""
        z0, inside = self.ctx.surface.lookup(self.poses[:, 0], self.poses[:, 1])
        self.z0 = z0
        self.alive &= inside
        self.history = np.zeros((1, READING_COLUMNS))
        self.rivals = np.empty((0, 3))
        if self.whole_map is not None:
            self.whole_map.reset()

    def begin_update(self, measurement: Measurement) -> None:
        self._between = None  # a step's background work ends with its step
        self._pending = measurement
        self._todo = np.flatnonzero(self.alive)
        self._cursor = 0
        self._suspicion = np.full(len(self.poses), -np.inf)

    def background(self, budget: Budget) -> bool:
        """With noise, the sweep of the whole map, a share at a time, then the survivors
        and its finds judged again (ARCHITECTURE.md "Bounded work")."""
        return True if self._between is None else self._between.work(budget)

    def _background(self, job: AnytimeJob) -> Iterator[int]:
        """Once the survivors are few enough to be judged: shares of the sweep until it has
        passed over the whole map once, a share a step after that (its finds then follow
        the readings); then the judgement again, with the finds."""
        sweep = self.whole_map
        assert sweep is not None
        if int(self.alive.sum()) > JUDGED:
            return
        first_pass = not sweep.checked
        while True:
            for screened, centres in sweep.run(self.history, take=job.take(CHUNK)):
                if len(centres):
                    self._found(gauss_newton(self.ctx.surface, centres, self.history,
                                             np.ones(len(self.history)),
                                             iterations=SWEEP_STEPS,
                                             max_move=sweep.start_reach))
                yield max(screened, 1)
            if not first_pass or sweep.checked or sweep.begun_at is None:
                break  # a share a step, or the whole map once, or too few readings to begin
        if self.ctx.surface.map.is_profile and sweep.checked:
            self._found(self._along_profile())
            yield 1
        self.verdict = self._judge()
        yield 1

    def _along_profile(self) -> np.ndarray:
        """A profile's every pose, half a sample apart either way along it, the best
        `RIVALS` polished onto the readings: the sweep's finds, polished once from its
        cells, can stop in the wrong basin of a periodic profile (a rack's ends, seed 21:
        6 mm from the truth, which then lost to its mirror image at the other end)."""
        extent = self.ctx.surface.map.extent[0]
        xs = np.arange(0.0, extent, 0.5 * self.ctx.surface.map.spacing)
        poses = np.column_stack([np.tile(xs, 2), np.zeros(2 * len(xs)),
                                 np.repeat([0.0, np.pi], len(xs))])
        best = poses[np.argsort(-self._log_likelihood(poses), kind="stable")[:4 * RIVALS]]
        return gauss_newton(self.ctx.surface, best, self.history, np.ones(len(self.history)),
                            iterations=SWEEP_STEPS, max_move=self.ctx.surface.map.spacing)

    def _log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        """Each pose's log likelihood on the readings, as the judge weighs it."""
        sensor = self.ctx.sensor
        return fit_log_likelihood(self.ctx.surface, poses, self.history,
                                  max(float(sensor.sigma), 0.01 * self.ctx.step_length),
                                  self.margin,
                                  float(getattr(sensor, "outlier_probability", 0.0)),
                                  float(getattr(sensor, "outlier_range_m", 1.0)))

    def _found(self, poses: np.ndarray) -> None:
        """Keep the sweep's finds beside those before: the best `RIVALS` distinct ones."""
        found = np.vstack([poses, self.rivals])
        order = distinct(found, self._log_likelihood(found), 0.25 * self.ctx.step_length,
                         np.deg2rad(5.0))
        self.rivals = found[order[:RIVALS]]

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
                self._between = AnytimeJob(self._background)
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
        if idx.size + len(self.rivals) == 0 or idx.size > JUDGED:
            return Verdict(None, np.empty((0, 3)), 0.0, None, 0.0, False,
                           f"{idx.size} poses of the table are left; they are judged once at "
                           f"most {JUDGED} remain" if idx.size else "")
        order = idx[np.argsort(self.sse[idx], kind="stable")]
        centres = np.vstack([self.poses[order], self.rivals])
        modes = Modes(centres=centres, masses=np.full(len(centres), 1.0 / len(centres)),
                      labels=np.arange(len(centres)))
        sensor = self.ctx.sensor
        verdict = judge(self.ctx.surface, self.history, modes, sigma=float(sensor.sigma),
                     noisy=True, step_length=self.ctx.step_length, rule=self.rule,
                     margin=5 * self.ctx.motion.position_sigma,
                     outlier_probability=float(getattr(sensor, "outlier_probability", 0.0)),
                     outlier_range=float(getattr(sensor, "outlier_range_m", 1.0)),
                     position_sigma=self.ctx.motion.position_sigma, previous=previous,
                     motions=self.motions, polish=6)
        assert self.whole_map is not None
        if verdict.converged and not self.whole_map.checked:  # the whole map has yet to agree
            verdict = dataclasses.replace(
                verdict, converged=False,
                held_back="the sweep of the whole map has not passed over every pose yet")
        return verdict

    # -- belief ----------------------------------------------------------------------------
    def estimate(self) -> Estimate:
        idx = np.flatnonzero(self.alive)
        v = self.verdict
        if self.noisy and v.fit is not None:  # the refined survivor (or find), judged
            return Estimate(pose=v.fit.pose, candidates=int(idx.size) + len(self.rivals),
                            converged=v.converged, held_back=v.held_back,
                            position_sd=v.fit.position_sd, heading_sd=v.fit.heading_sd,
                            mode_mass=v.mode_mass, runner_up=v.runner_up,
                            runner_up_mass=v.runner_up_mass, information=v.fit.information)
        if idx.size == 0:
            return Estimate(pose=None, candidates=0, converged=False)
        order = idx[np.argsort(self.sse[idx], kind="stable")]
        best = tuple(float(v) for v in self.poses[order[0]])
        runner = tuple(float(v) for v in self.poses[order[1]]) if idx.size > 1 else None
        pos_sd, head_sd = pose_spread(self.poses[idx])
        held_back = v.held_back if self.noisy else ""
        if idx.size == 1 and not self.noisy:  # the paper's rule, if the last pose is proven
            held_back = self._last_pose_unproven(self.poses[order[0]])
        return Estimate(pose=best, candidates=int(idx.size),
                        converged=idx.size == 1 and not self.noisy and not held_back,
                        position_sd=pos_sd, heading_sd=head_sd, mode_mass=1.0 / idx.size,
                        runner_up=runner, runner_up_mass=1.0 / idx.size if runner else 0.0,
                        held_back=held_back)

    def _felt(self) -> bool:
        """Whether the readings felt the surface's shape: heights that depart from every
        plane through them (height = c + a dx + b dy over the finger's displacements) by
        `FELT` steps or more. On a plain, or on an even slope, where each step reads the
        same wherever it is taken, only the map's edges and the table's coarse lattice
        leave a pose alone: one was declared 94 mm and 160 degrees off (a held-out plain
        with one 3 mm boss the finger never met), another 5 mm off on a tilted plane. (Not
        how well the readings pin the pose: noise-free the table is the localizer's
        premise, and peaks' flat corner pins its truth to 9 mm and 19 degrees only, where
        the table's neighbours, 10 mm and 33 degrees away, are told apart.)"""
        h = self.history
        design = np.column_stack([np.ones(len(h)), h[:, 0], h[:, 1]])
        coef, *_ = np.linalg.lstsq(design, h[:, 2], rcond=None)
        return float(np.max(np.abs(h[:, 2] - design @ coef))) > FELT * self.ctx.step_length

    def _last_pose_unproven(self, pose: np.ndarray) -> str:
        """Why the paper's rule may not declare the table's last pose, noise-free, or "".
        It must fit every reading: the band test passes poses that do not, and a start
        between the table's poses left one alone 54-94 mm off (held-out plains with one
        small feature). No image of it under a symmetry of the map may fit them too: the
        table may hold the truth's image and not the truth (a half-turn symmetric map, a
        flat plate: declared 170-224 mm off)."""
        readings = self.history[1:]
        if len(readings) == 0:
            return ""
        surface, margin = self.ctx.surface, 5 * self.ctx.motion.position_sigma
        r, on_map = residuals(surface, pose[np.newaxis], readings, margin)
        if not (on_map.all() and self.ctx.sensor.consistent(r).all()):
            return ("the table's last pose does not fit every reading: the start may lie "
                    "between the table's poses (a noisy run's localizer searches the whole "
                    "map)")
        if not self._felt():
            return ("the readings lie on one plane (a plain or an even slope), which reads the "
                    "same wherever it is stepped on: only the map's edges and the table's "
                    "coarse lattice leave it alone")
        twins = images(surface, pose, self.motions)
        apart = ((np.hypot(twins[:, 0] - pose[0], twins[:, 1] - pose[1])
                  > 0.25 * self.ctx.step_length)
                 | (np.abs(wrap_angle(twins[:, 2] - pose[2])) > np.deg2rad(5.0)))
        twins = twins[apart]
        if len(twins):  # polished onto the readings first: a symmetry found on a coarse
            # grid maps the surface onto itself only to a sample or so (a held-out half
            # turn's image at the map's centre missed, and its turn was declared)
            twins = gauss_newton(surface, twins, self.history, np.ones(len(self.history)),
                                 iterations=SWEEP_STEPS, max_move=0.25 * self.ctx.step_length)
            # heights only: where the map's edges stop a step is no part of its symmetry
            stepped = readings[:, 3:].any(axis=1)  # a blocked step's command (`reading_row`)
            r, _ = residuals(surface, twins, readings[~stepped, :3], margin)
            fits = (np.abs(r) <= IMAGE_FIT * self.ctx.step_length).all(axis=1)
            if fits.any():
                x, y, heading = twins[int(np.argmax(fits))]
                return (f"its image under a symmetry of the map, x {x * 1e3:.1f} mm, y "
                        f"{y * 1e3:.1f} mm, heading {np.rad2deg(heading) % 360:.1f} deg, "
                        "fits every reading too")
        return ""

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

