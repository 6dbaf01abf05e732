"""Algorithm IV: evolutionary Monte Carlo localization with a bounded pool (paper §3.4).

The paper proposed it and never built it. Here:

* a random initial pool of start poses over the whole map and every heading;
* each member stands for a range of poses (paper Eq. 4): its residuals are judged with a
  sd widened by how far a pose within that range could move each reading, so a coarse
  early pool is not wiped out by a sharp sensor; the range contracts every step;
* weights are the height likelihood of the whole history (the residuals of every reading
  are kept per member, so re-weighting at a new range costs arithmetic, not lookups);
* members far below the best are discarded; every member takes one vectorized
  Gauss-Newton step onto the readings (kept if it fits better); children are drawn around
  parents chosen by O(N) systematic resampling, more of them when the effective sample
  size is low;
* fresh members are injected (and the ranges widened) once every member fits poorly: the
  best of `scanned` random poses on the latest few readings, so a search of the whole
  map costs a few lookups per pose tried;
* one member per small (position, heading) cell is kept, so one mode's offspring cannot
  crowd out other modes; the best member of each plausible coarse cell is never cut for
  room; the rest is thinned to a capacity of `work / readings`, so the pool shrinks as
  the history grows and the work per step stays bounded;
* the plausible modes feed mode tracks (`tracks.py`) that only evidence removes, and on a
  periodic surface the leader's symmetric images join them (`symmetry.py`); the leading
  track is refined by least squares on all readings (`refine.py`) and declared only when
  `convergence.py` agrees, and once the checks of `declaration.py` let it: the turned
  check (the leader turned by every multiple of 45 degrees and moved anywhere on the map,
  where no turned pose may fit nearly as well: a part that repeats a feature turned, which
  the sweep's coarse cells pass over), its deep pass, and the certificate of the whole map.

The work per step is bounded by the pool's capacity and the number of readings, not by the
map's area (BENCHMARKS.md B3).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import ClassVar

import numpy as np

from service.bounds import Contraction, Count, Gate
from service.localization import bound_kernels, kernels
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
    group_modes,
    judge,
)
from service.localization.localizers.declaration import DeclarationChecks
from service.localization.localizers.fitting import (
    gauss_newton,
    log_likelihood,
    on_pose_space,
    residuals,
    sigmas,
    typical_slope,
)
from service.localization.localizers.pool import (
    AnytimeJob,
    effective_sample_size,
    niche,
    systematic_resample,
    thin,
)
from service.localization.localizers.refine import Fit
from service.localization.localizers.spread import pose_spread
from service.localization.localizers.sweep import Sweep, SweepSettings
from service.localization.localizers.symmetry import images, symmetries
from service.localization.localizers.tracks import ModeTracks
from service.localization.localizers.turned import Weighing

CHUNK = 4096
SCREEN_READINGS = 4
"""Readings a fresh candidate is screened on before it may join the pool."""
SWEEP_STEPS = 8
"""Gauss-Newton steps that polish a pose the sweep hands over onto every reading."""
SWEEPS_BETWEEN = 4
"""Sweep shares (`SweepSettings.cells_per_update` cells each) done between two updates,
while the finger moves (`Particles.background`)."""


class Particles:
    """Algorithm IV over a bounded, evolving pool of continuous start poses."""

    name: ClassVar[str] = "particles"

    def __init__(self, ctx: LocalizerContext, *, initial: Count = 20000, capacity: Count = 3000,
                 work: Count = 2000, min_capacity: Count = 200, children: Count = 100,
                 fresh: Count = 200, scanned: Count = 2000, polish: Count = 100_000,
                 drop: Gate = 40.0, contraction: Contraction = 0.6, rivals: Count = 32,
                 kept_modes: Count = 256,
                 rule: ConvergenceRule | None = None,
                 sweep: SweepSettings | None = None) -> None:
        kernels.warm_up()  # compile before the first update, not during it
        bound_kernels.warm_up()
        self.ctx = ctx
        self.initial, self.capacity, self.min_capacity = initial, capacity, min_capacity
        self.work_items = work
        self.children, self.fresh, self.polish, self.drop = children, fresh, polish, drop
        self.scanned = scanned
        self.contraction, self.rivals = contraction, rivals
        self.rule = rule or ConvergenceRule.for_map(ctx.surface.map.extent, ctx.step_length)
        step = ctx.step_length
        self.sigma = float(ctx.sensor.sigma)
        self.noisy = self.sigma > 1e-6
        self.slope = typical_slope(ctx.surface)
        self.margin = 5 * ctx.motion.position_sigma
        self.pos_range, self.head_range = 0.5 * step, np.deg2rad(10.0)
        self.pos_floor = max(0.02 * step, 2 * ctx.motion.position_sigma)
        self.head_floor = np.deg2rad(0.5)
        self.cells = (0.1 * step, np.deg2rad(2.0))
        self.mode_cells = (0.5 * step, np.deg2rad(15.0))
        self.same_pose = (0.25 * step, np.deg2rad(5.0))
        """Position and heading within which two polished poses are one mode."""
        self.fit_sd = max(self.sigma, 0.002 * step)
        """Reading sd at which polished poses are compared (floored: noise-free, 0.1 um)."""
        self.mode_drop = 20.0
        self.kept_modes = kept_modes
        self.outlier_p = float(getattr(ctx.sensor, "outlier_probability", 0.0))
        self.outlier_range = float(getattr(ctx.sensor, "outlier_range_m", 1.0))
        self.history = np.zeros((1, READING_COLUMNS))
        self.poses = np.empty((0, 3))
        self.resid = np.empty((0, 0))
        self.on_map = np.empty((0, 0), dtype=bool)
        self.ll = np.empty(0)
        self.fit: Fit | None = None
        self.mode_mass = 0.0
        self.runner_up: tuple[float, float, float] | None = None
        self.runner_up_mass = 0.0
        self.converged = False
        self.held_back = ""
        """Why the last judgement did not declare (`Verdict.held_back`)."""
        self.pending = False
        """The judge would declare the fit, the sweep or the declaration's checks have yet
        to allow it (`Estimate.pending`): the background judges it again when done."""
        self.tracks = ModeTracks()
        self._found_images = np.empty((0, 3))
        """Images of the leader the judge found by searching (`Verdict.found`): tracked."""
        self._searched_from: np.ndarray | None = None
        """The leader the judge last searched around its images from."""
        self.motions = symmetries(ctx.surface)
        self.sweep = Sweep(ctx.surface, step, self.sigma, self.margin, sweep or SweepSettings())
        self._job: AnytimeJob | None = None
        self._between: AnytimeJob | None = None
        """The work a declaration waits on, done while the finger moves (`background`)."""
        self._judge_ns = 0
        """How long the last judgement took: a hint for slicing, never for results."""
        self._sd_cache: tuple[tuple[int, float, float] | None, np.ndarray] = (None, np.empty(0))
        weighing = Weighing(ctx.surface, self.sigma, self.fit_sd, ctx.motion.position_sigma,
                            self.margin, self.outlier_p, self.outlier_range, step,
                            self.same_pose, self.rule.mode_mass)
        self._checks = DeclarationChecks(weighing, self.sweep, self.rule, SWEEP_STEPS)
        """The turned check, its deep pass and the certificate (`declaration.py`)."""

    # -- updates ---------------------------------------------------------------------------
    def start(self, first: Measurement) -> None:
        """The initial pool: uniform over the map and every heading."""
        self.history = np.zeros((1, READING_COLUMNS))
        self._sd_cache = (None, np.empty(0))
        self._checks.reset()
        self.tracks = ModeTracks()
        self._found_images, self._searched_from = np.empty((0, 3)), None
        self.sweep.reset()
        self.poses = self._random(self.initial)
        self.resid = np.zeros((len(self.poses), 0))
        self.on_map = np.ones((len(self.poses), 0), dtype=bool)
        self.ll = np.zeros(len(self.poses))

    def begin_update(self, measurement: Measurement) -> None:
        self._between = None  # a step's background work ends with its step
        self._job = AnytimeJob(lambda job: self._update(job, measurement))

    def work(self, budget: Budget) -> bool:
        done = True if self._job is None else self._job.work(budget)
        if done and self._job is not None:
            self._job = None
            self._between = AnytimeJob(self._background)
        return done

    def background(self, budget: Budget) -> bool:
        """The global checks a declaration waits on, done while the finger moves
        (ARCHITECTURE.md "Bounded work").

        * The sweep: up to `SWEEPS_BETWEEN` shares per step, only what the updates still to
          come before the rule's least readings could not cover themselves, until the map
          is covered once (later sweeps refresh the pool, a share per update). On a map of
          20 x 20 steps the updates cover it in time. On B3's 80-unit map a share per
          update held the declaration back to a median of 29 steps.
        * The turned check and its deep pass (a share a step, all of it once the leading
          mode is likely), and the certificate of a pose the next update may declare
          (`declaration.py`)."""
        return True if self._between is None else self._between.work(budget)

    def _background(self, job: AnytimeJob) -> Iterator[int]:
        needed = self.rule.min_readings_noisy if self.noisy else self.rule.min_readings
        per_update = self.sweep.settings.cells_per_update
        for _ in range(SWEEPS_BETWEEN):
            updates = max(needed - (len(self.history) - 1), 0)
            if self.sweep.checked or self.sweep.remaining <= updates * per_update:
                break
            yield from self._swept(job)
        if self.fit is None:
            return
        yield from self._checks.between_steps(np.asarray(self.fit.pose), self.history,
                                              self._reading_weights, self.mode_mass,
                                              self.noisy, self._add)
        if self.pending:  # the judge would declare: the checks just made may now allow it
            self.pending = False
            self.converged = self.sweep.checked and self._checks.clear(
                np.asarray(self.fit.pose), self.history, self._add)
            self.held_back = "" if self.converged else self._checks_words()

    def _update(self, job: AnytimeJob, m: Measurement) -> Iterator[int]:
        self.history = np.vstack([self.history, reading_row(m, self.ctx.walls)])
        reading = self.history[-1:]
        n = len(self.poses)
        column = np.empty(n)
        on_map = np.empty(n, dtype=bool)
        cursor = 0
        while cursor < n:  # the one pass over every member: sliced for the budget
            stop = min(n, cursor + job.take(CHUNK))
            r, ok = residuals(self.ctx.surface, self.poses[cursor:stop], reading, self.margin)
            column[cursor:stop], on_map[cursor:stop] = r[:, 0], ok[:, 0]
            yield stop - cursor
            cursor = stop
        self.resid = np.column_stack([self.resid, column])
        self.on_map = np.column_stack([self.on_map, on_map])
        # the ranges are those of the last full re-weighting (`_contract`): only the new
        # reading's term is new
        self.ll = self.ll + log_likelihood(column[:, np.newaxis], on_map[:, np.newaxis],
                                           self._sd()[-1:], self.outlier_p, self.outlier_range)
        self._discard()
        yield 1
        yield from self._polish(job)
        yield from self._breed(job)
        self._inject()
        yield 1
        yield from self._swept(job)
        yield from self._prune()
        self._contract()
        job.expect(self._judge_ns)  # the judgement is one slice: start it in a fresh call
        yield len(self.poses)
        started = time.monotonic_ns()
        self._judge()
        self._judge_ns = time.monotonic_ns() - started

    # -- the steps of one update -----------------------------------------------------------
    def _sd(self) -> np.ndarray:
        """Residual sd per reading at the current ranges; asked for many times an update,
        computed once per (readings, ranges)."""
        key = (len(self.history), self.pos_range, self.head_range)
        if self._sd_cache[0] != key:
            self._sd_cache = (key, sigmas(self.sigma, self.slope, self.history[1:],
                                          self.pos_range, self.head_range))
        return self._sd_cache[1]

    def _reading_weights(self) -> np.ndarray:
        """Gauss-Newton's weight of every reading, first contact included: 1 / sd^2 at the
        current ranges."""
        return 1.0 / np.concatenate([[self.sigma], self._sd()]) ** 2

    def _reweight(self) -> None:
        self.ll = log_likelihood(self.resid, self.on_map, self._sd(), self.outlier_p,
                                 self.outlier_range)

    def _keep(self, idx: np.ndarray) -> None:
        self.poses = self.poses[idx]
        self.resid, self.on_map, self.ll = self.resid[idx], self.on_map[idx], self.ll[idx]

    def _add(self, poses: np.ndarray) -> None:
        r, ok = residuals(self.ctx.surface, poses, self.history[1:], self.margin)
        ll = log_likelihood(r, ok, self._sd(), self.outlier_p, self.outlier_range)
        self.poses = np.vstack([self.poses, poses])
        self.resid = np.vstack([self.resid, r])
        self.on_map = np.vstack([self.on_map, ok])
        self.ll = np.concatenate([self.ll, ll])

    def _discard(self) -> None:
        """Drop members the readings rule out, relative to the best (a likelihood ratio)."""
        if len(self.ll):
            self._keep(np.flatnonzero(self.ll >= self.ll.max() - self.drop))

    def _polish(self, job: AnytimeJob) -> Iterator[int]:
        """Gauss-Newton on the `polish` best members: each slides onto the readings' fit nearby.

        A Lamarckian mutation: a member keeps what it learns, but never moves further than
        the range it stands for, so it cannot jump into another mode's basin. Members are
        independent, so the work is sliced by member without changing the result.
        """
        if len(self.poses) == 0 or len(self.history) < 2:
            return
        k = min(self.polish, len(self.poses))
        top = np.sort(np.argpartition(-self.ll, k - 1)[:k])
        w = self._reading_weights()
        max_move = max(2 * self.pos_range, 0.05 * self.ctx.step_length)
        cursor = 0
        while cursor < len(top):
            part = top[cursor:cursor + job.take(self._slice_members())]
            moved = gauss_newton(self.ctx.surface, self.poses[part], self.history, w,
                                 iterations=1, max_move=max_move)
            r, ok = residuals(self.ctx.surface, moved, self.history[1:], self.margin)
            ll = log_likelihood(r, ok, self._sd(), self.outlier_p, self.outlier_range)
            better = ll > self.ll[part]
            idx = part[better]
            self.poses[idx] = moved[better]
            self.resid[idx], self.on_map[idx], self.ll[idx] = r[better], ok[better], ll[better]
            cursor += len(part)
            yield len(part)

    def _breed(self, job: AnytimeJob) -> Iterator[int]:
        """Children around promising parents; a low effective sample size asks for more.

        All random draws happen first, so slicing the children's evaluation leaves the
        result (and the generator's stream) unchanged.
        """
        if len(self.poses) == 0:
            return
        w = np.exp(self.ll - self.ll.max())
        count = self.children * (2 if effective_sample_size(w) < 0.1 * len(w) else 1)
        parents = systematic_resample(w, count, self.ctx.rng)
        jitter = self.ctx.rng.standard_normal((count, 3)) * np.array(
            [self.pos_range, self.pos_range, self.head_range])
        children = on_pose_space(self.ctx.surface, self.poses[parents] + jitter)
        cursor = 0
        while cursor < count:
            part = children[cursor:cursor + job.take(self._slice_members())]
            self._add(part)
            cursor += len(part)
            yield len(part)

    def _slice_members(self) -> int:
        """Members per slice: about CHUNK readings' worth of lookups."""
        return max(1, CHUNK // max(1, len(self.history)))

    def _inject(self) -> None:
        """Wider ranges again once every member fits poorly, and fresh random members
        until the global sweep (`_swept`) has begun: the pool has lost the truth (or never
        held it) and must search again."""
        if len(self.poses) and len(self.history) > 1:
            z = self.resid / self._sd()
            best = float(np.min(np.sqrt(np.mean(np.where(self.on_map, z * z, 1e6), axis=1))))
            if best <= 3.0:
                return
            self.pos_range = max(self.pos_range, 0.25 * self.ctx.step_length)
            self.head_range = max(self.head_range, np.deg2rad(5.0))
            if self.sweep.begun_at is not None or self.sweep.checked:
                return  # the global sweep searches the whole map, systematically
        self._add(self._screened(self._random(self.scanned)))

    def _swept(self, job: AnytimeJob) -> Iterator[int]:
        """This update's share of the global sweep (`sweep.py`): the cells that could
        explain the readings, each polished onto them within its own reach, join the pool.
        However the truth was lost, it is back once a sweep has passed its cell."""
        w = self._reading_weights()
        for screened, centres in self.sweep.run(self.history, take=job.take(CHUNK)):
            if len(centres):
                self._add(gauss_newton(self.ctx.surface, centres, self.history, w,
                                       iterations=SWEEP_STEPS, max_move=self.sweep.start_reach))
            yield screened

    def _screened(self, candidates: np.ndarray) -> np.ndarray:
        """The `fresh` candidates that best fit the latest readings: a cheap first look
        (a few readings each) decides which are worth a full evaluation, so a wide search
        costs little more than a narrow one."""
        if len(self.history) <= 1 or len(candidates) <= self.fresh:
            return candidates[:self.fresh]
        latest = self.history[1:][-SCREEN_READINGS:]  # the readings `_sd` has an sd for
        r, ok = residuals(self.ctx.surface, candidates, latest, self.margin)
        ll = log_likelihood(r, ok, self._sd()[-len(latest):], self.outlier_p,
                            self.outlier_range)
        return candidates[np.sort(np.argpartition(-ll, self.fresh - 1)[:self.fresh])]

    def _prune(self) -> Iterator[int]:
        """One member per cell, then thin to a capacity that bounds the work per step.

        The work of an update is about pool size x readings, so the capacity is
        `work / readings` (clipped): a large pool while each member is cheap to test, a
        smaller one as the history grows and the pool converges (paper §3.4).
        """
        if len(self.poses) == 0:
            return
        before = len(self.poses)
        self._keep(niche(self.poses, self.ll, *self.cells, ordered=False))
        yield before
        self._discard()
        readings = len(self.history)  # what the next update will test each member on
        # the best member of every plausible coarse cell is a mode the pool must not lose
        # for want of room: only evidence may remove it (a periodic surface keeps many)
        leaders = self._leaders(self.kept_modes)
        cap = int(np.clip(self.work_items // readings, self.min_capacity, self.capacity))
        # and room beside them: leaders alone, one a mode, cannot follow their modes (a knurl
        # with hundreds alike, seed 270, declared a half turn off; while room beside them
        # was none, `thin` kept every member, 1,500 on plate:20:1 seed 9)
        cap = max(cap, len(leaders) + self.min_capacity)
        yield len(self.poses)
        if len(self.poses) > cap:
            rest = np.ones(len(self.poses), dtype=bool)
            rest[leaders] = False
            rest = np.flatnonzero(rest)
            fill = rest[thin(self._weights()[rest], cap - len(leaders), self.ctx.rng)]
            self._keep(np.sort(np.concatenate([leaders, fill])))

    def _leaders(self, limit: int) -> np.ndarray:
        """The best member of each plausible coarse cell, best first, at most `limit`."""
        plausible = np.flatnonzero(self.ll >= self.ll.max() - self.mode_drop)
        return plausible[niche(self.poses[plausible], self.ll[plausible], *self.mode_cells,
                               limit=limit)]

    def _contract(self) -> None:
        self.pos_range = max(self.pos_floor, self.pos_range * self.contraction)
        self.head_range = max(self.head_floor, self.head_range * self.contraction)
        self._reweight()

    def _judge(self) -> None:
        """Modes, the refined leading pose, and whether to declare it (convergence.py).

        The pool's plausible modes feed the mode tracks (`tracks.py`), which keep every
        distinct explanation of the readings until the readings rule it out; the leading
        mode's probability is its share among them.
        """
        previous = self.fit
        self.fit, self.converged, self.pending = None, False, False
        self.mode_mass, self.runner_up, self.runner_up_mass = 0.0, None, 0.0
        self.held_back = ""
        if len(self.poses) == 0:
            return
        step = self.ctx.step_length
        if len(self.history) < 4:  # fewer readings than unknowns: modes are not yet poses
            self.mode_mass = float(group_modes(self.poses, self._weights(), step,
                                               np.deg2rad(20.0), 1).masses[0])
            return
        track = dict(sd=self.fit_sd, position_tol=self.same_pose[0],
                     heading_tol=self.same_pose[1], margin=self.margin,
                     outlier_probability=self.outlier_p, outlier_range=self.outlier_range)
        leaders = self.poses[self._leaders(self.rivals)]
        lead = self.tracks.centres[0] if len(self.tracks.centres) else leaders[0]
        # a (near) symmetric surface: the leader's images join as candidates too
        self.tracks.update(self.ctx.surface, self.history,
                           np.vstack([leaders, images(self.ctx.surface, lead, self.motions),
                                      self._found_images]),
                           **track)
        shares = self.tracks.shares()
        modes = Modes(centres=self.tracks.centres, masses=shares,
                      labels=np.full(len(self.poses), -1))
        v = judge(self.ctx.surface, self.history, modes, sigma=self.sigma, noisy=self.noisy,
                  step_length=step, rule=self.rule, margin=self.margin,
                  outlier_probability=self.outlier_p, outlier_range=self.outlier_range,
                  polish=0, position_sigma=self.ctx.motion.position_sigma,
                  previous=None if previous is None else previous.pose,
                  # the leader's images are judged too: tracks hold at most 64 modes, a
                  # periodic map has up to hundreds of images, and the one that decides
                  # may be the one left out (egg-crate, seed 2: a half turn, declared)
                  motions=self.motions, search_images=self._search_images(lead),
                  refined_rivals=0, loose_mass=0.99)  # tracks are polished every update
        # declared only once a sweep has covered the whole map (`sweep.py`): a pool that
        # never held the truth has no rival to lose to
        self.fit, self.mode_mass = v.fit, v.mode_mass
        self._found_images = v.found  # tracked from the next update: found once
        if v.searched:
            self._searched_from = np.array(lead, dtype=np.float64)
        self.converged = v.converged and self.sweep.checked
        self.runner_up, self.runner_up_mass = v.runner_up, v.runner_up_mass
        if v.fit is not None:  # the polished modes and the fit join the pool
            self._add(np.vstack([self.tracks.centres[:self.rivals], [v.fit.pose]]))
            self.converged = self.converged and self._checks.clear(
                np.asarray(v.fit.pose), self.history, self._add)
        self.pending = v.converged and not self.converged
        self.held_back = v.held_back or ("" if self.converged else self._checks_words())

    def _checks_words(self) -> str:
        """Why the checks of the whole map hold a declaration the judge would make back."""
        if not self.sweep.checked:
            return "the sweep of the whole map has not passed over every pose yet"
        return ("the checks of the whole map (turned copies, the certificate) have not "
                "cleared it yet: a pose elsewhere may fit comparably")

    # -- helpers ---------------------------------------------------------------------------
    def _random(self, count: int) -> np.ndarray:
        x_max, y_max = self.ctx.surface.map.extent
        rng = self.ctx.rng
        x = rng.uniform(0.0, x_max, count)
        y = np.zeros(count) if self.ctx.surface.map.is_profile else rng.uniform(0.0, y_max, count)
        if self.ctx.surface.map.is_profile:
            heading = np.pi * rng.integers(0, 2, count)
        else:
            heading = rng.uniform(-np.pi, np.pi, count)
        return np.column_stack([x, y, heading])

    def _weights(self) -> np.ndarray:
        return np.exp(self.ll - self.ll.max()) if len(self.ll) else self.ll

    # -- belief ----------------------------------------------------------------------------
    def estimate(self) -> Estimate:
        if len(self.poses) == 0:
            return Estimate(pose=None, candidates=0, converged=False)
        w = self._weights()
        if self.fit is not None:
            pose = self.fit.pose
            pos_sd, head_sd = self.fit.position_sd, self.fit.heading_sd
        else:
            pose = tuple(float(v) for v in self.poses[int(np.argmax(w))])
            pos_sd, head_sd = pose_spread(self.poses, w)
        return Estimate(pose=pose, candidates=len(self.poses), converged=self.converged,
                        position_sd=pos_sd, heading_sd=head_sd, mode_mass=self.mode_mass,
                        runner_up=self.runner_up, runner_up_mass=self.runner_up_mass,
                        information=None if self.fit is None else self.fit.information,
                        pending=self.pending, held_back=self.held_back)

    def retains(self, pose: tuple[float, float, float], position_tol: float,
                heading_tol: float) -> bool | None:
        """True when the declared pose is `pose` within tolerance; None otherwise: a
        continuous pool never held `pose` exactly, so it cannot say it dropped it."""
        if not self.converged or self.fit is None:
            return None
        p = self.fit.pose
        close = (np.hypot(p[0] - pose[0], p[1] - pose[1]) <= position_tol
                 and abs(float(wrap_angle(p[2] - pose[2]))) <= heading_tol)
        return True if close else None

    def _search_images(self, lead: np.ndarray) -> bool:
        """Whether the judge should search around the leader's images: not while the
        leader stays within a map sample and a degree of where it was last searched from
        (its images, and so what the search finds, stay put; on a shell the search found
        nothing in 42 updates running, a millisecond each)."""
        last = self._searched_from
        return last is None or bool(
            np.hypot(*(lead[:2] - last[:2])) >= self.ctx.surface.map.spacing
            or abs(float(wrap_angle(lead[2] - last[2]))) >= np.deg2rad(1.0))

    def hypotheses(self, limit: int | None = None) -> Hypotheses:
        w = self._weights()
        order = np.argsort(-w, kind="stable")
        if limit is not None:
            order = order[:limit]
        # a floor far below any real belief keeps every listed hypothesis drawable
        weights = np.maximum(w[order], 1e-12)
        total = weights.sum()
        weights = weights / total if total > 0 else np.full(len(order), 1.0 / max(len(order), 1))
        return Hypotheses(poses=self.poses[order], weights=weights)
