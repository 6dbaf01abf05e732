"""Algorithm III for a held object: a table of poses, each reading removing those that
cannot fit (paper §3.3), then the same honest judgement as every localizer.

The table holds every pose under which the first finger's first reading touches the
object: headings every `heading_step`, and for each, the outline points under that
fingertip every `arc_step` of arc (`contour_fit.poses_through`). A reading eliminates the
poses whose residual exceeds the sensor's gate plus the table's own coarseness (a table
pose may be half a cell off the truth); the slack contracts as the survivors are
Gauss-Newton polished onto the readings, so the test tightens to the sensor's gate. When
the fingers carry the object, every survivor moves through the motion model. With noise a
reading can eliminate the truth, so the survivors are judged like every other localizer's
modes (`object_judge.judge`), never declared for standing alone.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

import numpy as np

from service.bounds import Bound, Gate
from service.localization.localizers.base import Budget, Estimate, Hypotheses
from service.localization.localizers.contour_fit import (
    distinct_places,
    gauss_newton,
    poses_through,
    residuals,
)
from service.localization.localizers.convergence import ConvergenceRule
from service.localization.localizers.object_base import (
    HandMeasurement,
    ObjectContext,
    carry_poses,
    object_rule,
)
from service.localization.localizers.object_judge import TrackJudged
from service.localization.localizers.object_tracks import ObjectTracks
from service.localization.localizers.pool import niche
from service.localization.localizers.refine import Fit
from service.localization.localizers.shared_error import offset_log_likelihood_of
from service.localization.localizers.spread import pose_spread
from service.localization.objects import kernels
from service.localization.objects.symmetry import near_symmetries

POLISHED = 3000
"""Survivors are polished once no more than this many remain."""


HeadingStep = Annotated[float, Bound("float", lo=1e-4, hi=float(np.pi / 2), unit="rad")]
ArcStep = Annotated[float, Bound("float", lo=1e-5, hi=0.05, unit="m")]
HEADING_STEP = float(np.deg2rad(2.0))

class ObjectElimination(TrackJudged):
    """Algorithm III over a table of object poses."""

    name: ClassVar[str] = "elimination"

    def __init__(self, ctx: ObjectContext, *, heading_step: HeadingStep = HEADING_STEP,
                 arc_step: ArcStep = 0.0005, gate: Gate = 5.0,
                 rule: ConvergenceRule | None = None) -> None:
        kernels.warm_up()
        self.ctx = ctx
        self.heading_step, self.arc_step, self.gate = heading_step, arc_step, gate
        self.rule = rule or object_rule()
        self.sigma = ctx.sigma
        self.noisy = float(ctx.sensor.sigma) > 1e-6
        self.motions = near_symmetries(ctx.field)
        lever = ctx.field.contour.max_radius + float(np.max(ctx.radii))
        self.slack = 0.5 * (arc_step + heading_step * lever)
        """How far a reading may sit from a table pose's prediction because the table is
        coarse (half a cell of arc and heading)."""
        self.poses = np.empty((0, 3))
        self.points, self.radii = np.empty((0, 2)), np.empty(0)
        self.last_centres = np.empty((0, 2))
        self.places_before, self.epoch = 0, 0
        self.tracks = ObjectTracks()
        self.fit: Fit | None = None
        self.converged = False
        self.mode_mass, self.runner_up, self.runner_up_mass = 0.0, None, 0.0
        self._queued: HandMeasurement | None = None

    def start(self, first: HandMeasurement) -> None:
        centres = np.asarray(first.centres, dtype=np.float64)
        self.poses = poses_through(self.ctx.field, centres[0], float(self.ctx.radii[0]),
                                   self.heading_step, self.arc_step)
        self.points, self.radii = np.empty((0, 2)), np.empty(0)
        self.tracks = ObjectTracks()
        self.places_before, self.epoch = 0, 0
        self.last_centres = centres
        self.begin_update(first)
        self.work(Budget.unlimited())

    def begin_update(self, measurement: HandMeasurement) -> None:
        self._awaiting = None  # a check of the last verdict: new readings make a new one
        self._queued = measurement

    def work(self, budget: Budget) -> bool:
        """One update per call: the table shrinks fast, so a slice is short."""
        if self._queued is not None:
            m, self._queued = self._queued, None
            self._update(m)
        return True

    def _update(self, m: HandMeasurement) -> None:
        centres = np.asarray(m.centres, dtype=np.float64)
        if m.carried is not None:
            self._carry(*m.carried)
        moved = list(m.moved)
        self.points = np.vstack([self.points, centres[moved]])
        self.radii = np.concatenate([self.radii, self.ctx.radii[moved]])
        self.last_centres = centres
        if len(self.poses) <= POLISHED:  # polished survivors earn a tighter test
            self.poses = gauss_newton(self.ctx.field, self.poses, self.points, self.radii,
                                      iterations=2, max_move=self.slack)
            self.slack = max(0.5 * self.slack, 0.0)
        tolerance = self.gate * self.sigma + self.slack
        r = residuals(self.ctx.field, self.poses, centres[moved], self.ctx.radii[moved])
        self.poses = self.poses[np.all(np.abs(r) <= tolerance, axis=1)]
        self._judge()

    def _carry(self, moves: np.ndarray, rolls: np.ndarray) -> None:
        self.poses = carry_poses(self.ctx, self.poses, self.last_centres, moves, rolls)
        self.tracks.carry(self.ctx, self.last_centres, np.asarray(moves, dtype=np.float64),
                          np.asarray(rolls, dtype=np.float64), self.points, self.radii)
        self.places_before += distinct_places(self.points, 0.25 * self.ctx.scale)
        self.points, self.radii = np.empty((0, 2)), np.empty(0)
        self.epoch += 1
        self.fit = None
        # the motion's noise moves every survivor off its reading by about this much
        self.slack = max(self.slack, 0.05 * self.ctx.scale)

    def _judge(self) -> None:
        previous = self.fit
        self.fit, self.converged, self.leader = None, False, None
        if len(self.poses) == 0:
            return
        score = -np.arange(len(self.poses), dtype=np.float64)  # survivors are equal: any
        leaders = niche(self.poses, score, 0.5 * self.ctx.scale, np.deg2rad(15.0), limit=32)
        self._judge_leaders(self.poses[leaders], np.zeros(len(leaders)), previous)

    def _found(self, poses: np.ndarray) -> None:
        """Poses the whole-object check found join the table: they explain the readings as
        well as the leader does, and the policy must see them."""
        self.poses = np.vstack([self.poses, poses])

    def estimate(self) -> Estimate:
        if self.fit is not None:
            return Estimate(pose=self.fit.pose, candidates=len(self.poses),
                            converged=self.converged, position_sd=self.fit.position_sd,
                            heading_sd=self.fit.heading_sd, mode_mass=self.mode_mass,
                            runner_up=self.runner_up, runner_up_mass=self.runner_up_mass,
                            pending=self.pending, held_back=self.held_back)
        if len(self.poses) == 0:
            return Estimate(pose=None, candidates=0, converged=False)
        pos_sd, head_sd = pose_spread(self.poses)
        return Estimate(pose=self.leader or tuple(float(v) for v in self.poses[0]),
                        candidates=len(self.poses), converged=False, position_sd=pos_sd,
                        heading_sd=head_sd, mode_mass=self.mode_mass,
                        runner_up=self.runner_up if self.leader else None,
                        runner_up_mass=self.runner_up_mass if self.leader else 0.0)

    def hypotheses(self, limit: int | None = None) -> Hypotheses:
        """Survivors, weighted by how well they fit the readings since the last carry, their
        shared offset allowed (as `ObjectParticles.hypotheses`)."""
        if len(self.poses) == 0:
            return Hypotheses(poses=self.poses, weights=np.empty(0))
        if len(self.points):
            r = residuals(self.ctx.field, self.poses, self.points, self.radii)
            ll = offset_log_likelihood_of(self.ctx, r, max(self.sigma, 1e-9), 1.0)
        else:
            ll = np.zeros(len(self.poses))
        order = np.argsort(-ll, kind="stable")[:limit]
        w = np.exp(ll[order] - ll[order].max())
        return Hypotheses(poses=self.poses[order], weights=w / w.sum())
