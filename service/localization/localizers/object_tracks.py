"""The mode tracks of a held object: the distinct poses that explain the readings, each
with the evidence it carries through manipulations (`object_judge` weighs them).

As for a finger (`tracks.py`): the poses are kept as tracks until evidence removes them,
never for want of room. When the fingers carry the object, each track moves through the
motion model and keeps the evidence it had as its prior; its score is that prior plus the
fit to the readings since, and the readings from before move with it.
"""

from __future__ import annotations

import numpy as np

from service.localization.localizers.base import wrap_angle
from service.localization.localizers.contour_fit import gauss_newton
from service.localization.localizers.convergence import distinct
from service.localization.localizers.object_base import ObjectContext, carry_poses
from service.localization.localizers.shared_error import offset_log_likelihood, patch_temper

CARRIED_SD = 1e-4
"""Metres: the least sd a carry adds to the readings it moves. They move with the track's
pose, fitted then on the few readings it had, not with the truth's; without noise the
motion model added nothing, readings carried through a few turns missed a track at the
truth by up to 0.16 mm against a 5 um sd, and three fingers on keyed:0 (seed 0) kept
turning the object until their 100 steps ran out, undeclared."""


def tolerance(ctx: ObjectContext) -> tuple[float, float]:
    """Position (metres) and heading (radians) within which two poses are one, as a success
    is judged (B2's: a quarter of the scale, 5 degrees)."""
    return 0.25 * ctx.scale, float(np.deg2rad(5.0))


def near(a: np.ndarray, b: np.ndarray, position_tol: float, heading_tol: float) -> np.ndarray:
    """(len(a), len(b)) mask of pose pairs within tolerance of each other."""
    d_pos = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    d_head = np.abs(wrap_angle(a[:, None, 2] - b[None, :, 2]))
    return (d_pos <= position_tol) & (d_head <= heading_tol)


class ObjectTracks:
    """Up to `limit` polished mode centres, each with the evidence it carries (`prior`), its
    score on the readings since the last manipulation (`ll`), and the readings from before
    it (`felt`): a track that was carried knows where its own motion put its earlier
    readings, so its fit may use them too, with the motion's noise added.

    Evidence counts as independent only as far as the readings are (`patch_temper`): the latest
    readings' score is tempered by their own patches, and what a carry makes the prior is
    kept tempered as it was. Tempered afresh by the readings since the turn instead, the
    evidence from before counted in full once the few readings since lay in distinct
    patches: 12.2 nats for an image of a rounded triangle within 0.73 mm of its 120-degree
    turn where it had counted 5.5, and the image was declared (a helper's outline, seed 1,
    three fingers).

    A track's score allows the readings' shared offset (`shared_error.offset_log_likelihood`),
    as the judge's final weighing does: weighed without it, the truth's track on a slender
    outline lost 19 nats before a turn where the judge saw 0.7, carried that as its prior,
    and the half-turned image was declared (a helper's outline, seed 8, three fingers)."""

    def __init__(self, limit: int = 32, drop: float = 30.0) -> None:
        self.limit, self.drop = limit, drop
        self.centres = np.empty((0, 3))
        self.prior = np.empty(0)
        self.ll = np.empty(0)
        self.felt: list[np.ndarray] = []
        """Per track (K, 4): earlier readings moved as the track's motions moved the object
        (hand frame), their tip radius and the variance those motions added."""
        self.carries = np.empty(0, dtype=np.int64)
        """Per track, how many manipulations it was carried through."""
        self.temper = 1.0
        """How much of `ll` is independent evidence (`patch_temper` of the latest readings)."""

    @property
    def total(self) -> np.ndarray:
        return self.prior + self.temper * self.ll

    def best_prior(self) -> float:
        """The prior of the track that leads (0 with none)."""
        return float(self.prior[int(np.argmax(self.total))]) if len(self.centres) else 0.0

    def update(self, ctx: ObjectContext, points: np.ndarray, radii: np.ndarray,
               candidates: np.ndarray, candidate_prior: np.ndarray, *, sd: float,
               position_tol: float, heading_tol: float) -> None:
        """Add `candidates` far from every track, polish all, drop the clear losers."""
        if len(candidates):
            fresh = ~np.any(near(candidates, self.centres, 2 * position_tol, 2 * heading_tol),
                            axis=1)
            room = max(self.limit - len(self.centres), 0)
            take = np.flatnonzero(fresh)[:room]
            self.centres = np.vstack([self.centres, candidates[take]])
            self.prior = np.concatenate([self.prior, candidate_prior[take]])
            self.felt += [np.empty((0, 4)) for _ in take]
            self.carries = np.concatenate([self.carries, np.zeros(len(take), dtype=np.int64)])
        if len(self.centres) == 0:
            self.ll = np.empty(0)
            return
        if len(points):
            self.centres = gauss_newton(ctx.field, self.centres, points, radii, iterations=2,
                                        max_move=position_tol)
            self.ll = offset_log_likelihood(ctx, self.centres, points, radii, sd, 1.0)
        else:
            self.ll = np.zeros(len(self.centres))
        self.temper = patch_temper(ctx, points)
        total = self.total
        keep = distinct(self.centres, total, position_tol, heading_tol)
        keep = keep[total[keep] >= total[keep[0]] - self.drop]
        self.centres, self.prior, self.ll = self.centres[keep], self.prior[keep], self.ll[keep]
        self.felt = [self.felt[i] for i in keep]
        self.carries = self.carries[keep]

    def carry(self, ctx: ObjectContext, centres: np.ndarray, moves: np.ndarray,
              rolls: np.ndarray, points: np.ndarray, radii: np.ndarray) -> None:
        """Every track moved as the rolling model predicts; its evidence becomes its prior,
        and the readings since the last carry (`points`, hand frame) join what it felt."""
        if len(self.centres) == 0:
            return
        total = self.total
        self.prior = total - total.max()
        self.ll = np.zeros(len(self.centres))
        moved = carry_poses(ctx, self.centres, centres, moves, rolls, noisy=False)
        lever = ctx.field.contour.max_radius + float(np.max(ctx.radii))
        latest = np.column_stack([points, radii, np.zeros(len(points))])
        for i, (before, after) in enumerate(zip(self.centres, moved, strict=True)):
            turn = abs(float(wrap_angle(after[2] - before[2])))
            shift = float(np.hypot(*(after[:2] - before[:2])))
            # the motion model's noise on this carry, seen at the reading's lever
            spread = max((ctx.motion.fraction * (turn * lever + shift)) ** 2 / ctx.substeps
                         + (ctx.motion.direction_sigma * shift) ** 2, CARRIED_SD**2)
            felt = np.vstack([self.felt[i], latest])
            felt[:, :2] = from_object(to_object(felt[:, :2], before), after)
            felt[:, 3] += spread
            self.felt[i] = felt
        self.centres = moved
        self.carries = self.carries + 1

    def adopt(self, ctx: ObjectContext, poses: np.ndarray, points: np.ndarray,
              radii: np.ndarray, *, sd: float, position_tol: float, heading_tol: float
              ) -> None:
        """Track `poses` the localizer never kept (found by the whole-object check), far
        from every track, with the best track's prior (`best_prior`): what a track carried
        cannot be asked of them, so they are not held to it. None join a full set of
        tracks: the check then refuses again at the next declaration."""
        if len(poses) == 0:
            return
        fresh = poses[~np.any(near(poses, self.centres, 2 * position_tol, 2 * heading_tol),
                              axis=1)][:max(self.limit - len(self.centres), 0)]
        if len(fresh) == 0:
            return
        self.centres = np.vstack([self.centres, fresh])
        self.prior = np.concatenate([self.prior, np.full(len(fresh), self.best_prior())])
        self.ll = np.concatenate([self.ll, offset_log_likelihood(ctx, fresh, points, radii, sd,
                                                                  1.0)])
        self.felt += [np.empty((0, 4)) for _ in fresh]
        self.carries = np.concatenate([self.carries, np.zeros(len(fresh), dtype=np.int64)])

    def history(self, i: int, points: np.ndarray, radii: np.ndarray, sigma: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track i's readings: what it felt before (where its motions put them), then the
        readings since; their radii and sd."""
        felt = self.felt[i]
        return (np.vstack([felt[:, :2], points]), np.concatenate([felt[:, 2], radii]),
                np.sqrt(sigma**2 + np.concatenate([felt[:, 3], np.zeros(len(points))])))

    def shares(self) -> np.ndarray:
        if len(self.centres) == 0:
            return np.empty(0)
        w = np.exp(self.total - self.total.max())
        return w / w.sum()


def to_object(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (n, 2) of the hand plane in the frame of an object at `pose` (3,)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    w = np.asarray(points) - pose[:2]
    return np.column_stack([c * w[:, 0] + s * w[:, 1], -s * w[:, 0] + c * w[:, 1]])


def from_object(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (n, 2) of an object at `pose` (3,) in the hand plane: `to_object` undone."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.column_stack([c * points[:, 0] - s * points[:, 1] + pose[0],
                            s * points[:, 0] + c * points[:, 1] + pose[1]])
