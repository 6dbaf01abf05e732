"""Where a fingertip may meet a sharp convex corner before the model says it does.

A tip rolling along a face towards a sharp convex corner (a square's, a lens's tip) touches
the corner's vertex only once its centre passes over it, in the model. The world's outline
differs from the model's by a fraction of a millimetre, and where the face lies a depth d
inside the vertex, a tip of radius r meets the vertex about sqrt(2 r d) earlier: 2.8 mm for
an 8 mm tip and 0.5 mm. Its normal then points from the vertex to its centre, turned from
the face's by up to 20 degrees, and a grasp the model holds at 2 N may slip (three fingers
on a held-out 40 mm square, seed 26: 1.97 N under the true pose in the model after a roll,
-0.29 N in the world, whose tip met the vertex 1.5 mm before the model's reached it).

So where a tip's centre lies within its radius and `REACH` of a sharp corner's vertex, the
world may rest it on the vertex: the grasp's quality there is any of the model's and the
one with that normal (`grasp.hand_quality`, `beside_corners`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.localization.memo import kept
from service.localization.models import rotate
from service.localization.objects.contour import Contour

ANGLE = np.deg2rad(20.0)
"""Least turn of the outline within `ARC` that makes a sharp corner: a 4 mm rounding turns
it by 14 degrees over a millimetre, a 20 mm circle by 3."""
ARC = 0.001
"""Metres of outline over which a corner's turn is summed (a polyline turns a corner over a
few vertices)."""
REACH = 0.0003
"""Metres by which the world's outline may lie inside the model's at a corner: one and a
half sds of B2's outline mismatch (0.2 mm). Three fingers on held-out outlines: at 0.2 mm a
lens (seed 16) and a square (seed 25) still dropped; at 0.6 mm (three sds) a hexagon with
1 mm roundings localized 27 of 40 runs instead of 39; at 0.3 mm, 33, and neither dropped."""


@dataclass(frozen=True, eq=False)
class Corners:
    """The sharp convex corners of one outline, in the object's frame."""

    points: np.ndarray
    """(K, 2) the corners' vertices."""
    tree: cKDTree | None


def corners(contour: Contour) -> Corners:
    """The sharp convex corners of `contour`, kept while the contour lives."""
    return kept(contour, ("corners",), lambda: _find(contour))


def _find(contour: Contour) -> Corners:
    p = np.asarray(contour.points, dtype=np.float64)
    if contour.polygon.exterior.is_ccw is False:
        p = p[::-1]
    before = p - np.roll(p, 1, axis=0)
    after = np.roll(p, -1, axis=0) - p
    turn = np.arctan2(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0],
                      np.einsum("ij,ij->i", before, after))  # counter-clockwise: convex > 0
    length = np.hypot(*after.T)
    arc = np.concatenate([[0.0], np.cumsum(length)])[:-1]
    total = arc[-1] + length[-1]
    # each vertex's window of +-ARC/2 of outline, found on the outline laid out three times
    # (it is closed): a sum of turns and a sharpest vertex per window, in O(N log N)
    around = np.concatenate([arc - total, arc, arc + total])
    turns = np.tile(turn, 3)
    lo = np.searchsorted(around, arc - ARC / 2, side="left")
    hi = np.searchsorted(around, arc + ARC / 2, side="right")
    summed = np.concatenate([[0.0], np.cumsum(turns)])
    summed = summed[hi] - summed[lo]
    candidates = np.flatnonzero((summed >= ANGLE) & (turn > 0))
    found = p[[i for i in candidates if turn[i] >= turns[lo[i]:hi[i]].max()]]
    if len(found) == 0:
        return Corners(np.empty((0, 2)), None)
    return Corners(found, cKDTree(found))


def any_corners(contour: Contour) -> bool:
    """Whether `contour` has a sharp convex corner."""
    return corners(contour).tree is not None


def beside(contour: Contour, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
           reach: float = REACH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tips within their radius and `reach` of a sharp corner under each pose: (rows,
    fingers) indices (m,) into `poses` (B, 3) and `centres` (B, n, 2), and the normal (m, 1,
    2) a tip resting on the corner's vertex would have, in the hand frame."""
    found = corners(contour)
    if found.tree is None:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 1, 2))
    rows, fingers, normals = [], [], []
    for f, radius in enumerate(radii):
        w = centres[:, f] - poses[:, :2]
        local = np.column_stack(rotate(-poses[:, 2], w[:, 0], w[:, 1]))
        distance, k = found.tree.query(local, distance_upper_bound=float(radius) + reach)
        near = np.flatnonzero(np.isfinite(distance) & (distance > 0))
        if len(near) == 0:
            continue
        n = (local[near] - found.points[k[near]]) / distance[near, None]  # object frame
        normals.append(np.stack(rotate(poses[near, 2], n[:, 0], n[:, 1]), axis=-1)[:, None])
        rows.append(near)
        fingers.append(np.full(len(near), f))
    if not rows:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 1, 2))
    return np.concatenate(rows), np.concatenate(fingers), np.concatenate(normals)
