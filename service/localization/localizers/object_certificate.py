"""The whole-object check before a held object's pose is declared: every pose the readings
allow is asked, not only the poses the localizer kept.

A pool that lost the truth weighs only what it kept. A single finger on blob:12 (seed 12,
the object clamped) declared a pose 177 degrees off at 0.9997: the truth was never
tracked, yet it fitted the readings 2.7 nats better than the declared pose.

Every pose that explains the readings puts the object against each of them, within the
noise. So the poses through one reading, the most certain (`contour_fit.poses_through`:
every `HEADING_STEP` of heading, every `ARC_STEP` of outline under the fingertip), cover
them all. Each is screened on up to `SCREEN` readings, with the sd widened by how far half
a grid step can move each reading. The best `TOP` distinct poses beyond the tolerance are
polished onto every reading, and the judge weighs them as it weighs its rivals
(`object_judge.confirm`).

After a turn the readings are the leader's history, as its own motions carried them: a
pose the pool lost is judged on them as they lie, not as its own motions would have
carried them (the leader's images are judged alike, `object_judge._images`).
"""

from __future__ import annotations

import numpy as np

from service.localization.localizers.contour_fit import gauss_newton, poses_through, residuals
from service.localization.localizers.convergence import distinct, within
from service.localization.localizers.fitting import log_likelihood
from service.localization.objects.field import ContactField

HEADING_STEP = float(np.deg2rad(5.0))
ARC_STEP = 0.002
"""Metres of outline between the grid's contact points."""
SCREEN = 6
"""Most readings the grid is screened on (spread over the history, the anchor added)."""
SCREENED = 256
"""Best screened poses the distinct candidates are drawn from."""
TOP = 16
"""Distinct candidates polished onto every reading."""
POLISH = 8
"""Gauss-Newton steps a candidate takes."""


def rivals_beyond(field: ContactField, points: np.ndarray, radii: np.ndarray,
                  pose: np.ndarray, *, sd: float | np.ndarray, outlier_probability: float,
                  outlier_range: float, position_tol: float, heading_tol: float
                  ) -> np.ndarray:
    """The poses (k, 3), polished onto every reading, that explain `points` (each of sd
    `sd`) best among those further than the tolerance from `pose` (in place or in
    heading), best first."""
    if len(points) == 0:
        return np.empty((0, 3))
    sd = np.broadcast_to(np.asarray(sd, dtype=np.float64), (len(points),))
    anchor = int(np.argmin(sd))  # the most certain: carried readings carry their motion's error
    poses = poses_through(field, points[anchor], float(radii[anchor]), HEADING_STEP, ARC_STEP)
    use = np.unique(np.append(
        np.linspace(0, len(points) - 1, min(SCREEN, len(points))).astype(int), anchor))
    lever = np.hypot(*(points[use] - points[anchor]).T)
    wide = np.sqrt(sd[use] ** 2 + (lever * HEADING_STEP / 2) ** 2 + (ARC_STEP / 2) ** 2)
    r = residuals(field, poses, points[use], radii[use])
    score = log_likelihood(r, np.ones(r.shape, dtype=bool), wide, outlier_probability,
                           outlier_range)
    score = np.where(np.isfinite(score), score, -np.inf)
    score[within(poses, pose, position_tol, heading_tol)] = -np.inf
    best = np.argpartition(-score, min(SCREENED, len(score)) - 1)[:SCREENED]
    best = best[np.isfinite(score[best])]
    if len(best) == 0:
        return np.empty((0, 3))
    best = best[np.argsort(-score[best], kind="stable")]
    keep = best[distinct(poses[best], score[best], position_tol, heading_tol)][:TOP]
    polished = gauss_newton(field, poses[keep], points, radii, 1.0 / sd**2,
                            iterations=POLISH, max_move=position_tol)
    return polished[~within(polished, pose, position_tol, heading_tol)]
