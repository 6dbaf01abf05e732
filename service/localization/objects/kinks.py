"""Where a fingertip bridges a hollow narrower than itself: the kinks of the dilated contour.

A tip of radius r rests with its centre on the contour dilated by r (Eq. 7). Where the object
has a hollow narrower than the tip - a notch, a knob's valley, the gap between a gear's
teeth - the dilated contour has a concave corner, a kink: on it the tip touches both sides at
once; a hair to either side it touches one, and its normal has turned by the corner's whole
angle (60 degrees in the valleys of a five-lobed knob under an 8 mm tip). Everywhere else
the normal turns smoothly as the tip rolls.

The model's outline differs from the world's by a fraction of a millimetre, and a reading by
the sensor's noise, so where the model puts a tip beside a kink the world may put it on the
kink or on its other side. There the grasp's quality is not the model's one value but any of
three: with the tip on either side, or bridging (the kink's own normal, which a distance
field's gradient gives on the kink). Two fingers on a knob, one tip in a valley: the grasp
held 6 N in the world, and -0.36 N under the model at the true pose (its tip settled on one
side), so the gate took every pose near the truth for one that could not hold the object,
trusted the one pose left (1 % of the weight, 101 degrees off), and the first roll dropped
the object (a five-lobed knob of a held-out check, seed 28). The gate now counts a pose as
one the world may be in by the most the grasp could hold there (`grasp.hand_quality`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy.spatial import cKDTree

from service.localization.memo import kept
from service.localization.models import rotate
from service.localization.objects.contour import Contour

ANGLE = np.deg2rad(6.0)
"""Least turn of the dilated contour at a vertex that counts as a kink: a polyline's own
corners turn it by a degree or two."""
REACH = 0.001
"""Metres from a kink within which a tip the model puts beside it may rest anywhere on it in
the world: three sds of B2's outline mismatch (0.2 mm) and two of its reading noise
(0.1 mm) make 0.8 mm, taken up to 1 mm."""
_QUAD_SEGMENTS = 16


@dataclass(frozen=True, eq=False)
class Kinks:
    """The kinks of one contour dilated by one tip radius, in the object's frame."""

    points: np.ndarray
    """(K, 2) where a tip centre bridges a hollow."""
    normals: np.ndarray
    """(K, 3, 2) outward unit normals there: on one side, bridging, on the other."""
    tree: cKDTree | None


def kinks(contour: Contour, radius: float) -> Kinks:
    """The kinks of `contour` dilated by `radius`, kept while the contour lives."""
    return kept(contour, ("kinks", float(radius)), lambda: _find(contour, float(radius)))


def _find(contour: Contour, radius: float) -> Kinks:
    ring = contour.polygon.buffer(radius, quad_segs=_QUAD_SEGMENTS).exterior
    if not ring.is_ccw:
        ring = shapely.LinearRing(np.asarray(ring.coords)[::-1])
    p = np.asarray(ring.coords)[:-1]
    before = p - np.roll(p, 1, axis=0)
    after = np.roll(p, -1, axis=0) - p
    turn = np.arctan2(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0],
                      np.einsum("ij,ij->i", before, after))
    corner = np.flatnonzero(turn < -ANGLE)  # counter-clockwise: a concave corner turns right
    if len(corner) == 0:
        return Kinks(np.empty((0, 2)), np.empty((0, 3, 2)), None)
    sides = np.stack([_outward(before[corner]), _outward(after[corner])], axis=1)
    bridge = sides.sum(axis=1)
    bridge /= np.linalg.norm(bridge, axis=1, keepdims=True)
    normals = np.stack([sides[:, 0], bridge, sides[:, 1]], axis=1)
    return Kinks(p[corner], normals, cKDTree(p[corner]))


def _outward(edges: np.ndarray) -> np.ndarray:
    """Unit outward normals of a counter-clockwise ring's edges (their right-hand side)."""
    n = np.column_stack([edges[:, 1], -edges[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def any_kinks(contour: Contour, radii: np.ndarray) -> bool:
    """Whether the contour dilated by any of `radii` has a kink (else a tip is never beside
    one, and judging it so would repeat the model's quality)."""
    return any(kinks(contour, float(r)).tree is not None for r in radii)


def beside(contour: Contour, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
           reach: float = REACH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tips within `reach` of a kink under each pose: (rows, fingers) indices (m,) into
    `poses` (B, 3) and `centres` (B, n, 2), and the kink's three normals (m, 3, 2) turned
    into the hand frame by the row's pose."""
    rows, fingers, normals = [], [], []
    for f, radius in enumerate(radii):
        found = kinks(contour, float(radius))
        if found.tree is None:
            continue
        w = centres[:, f] - poses[:, :2]
        local = np.column_stack(rotate(-poses[:, 2], w[:, 0], w[:, 1]))
        distance, k = found.tree.query(local, distance_upper_bound=reach)
        near = np.flatnonzero(np.isfinite(distance))
        if len(near) == 0:
            continue
        n = found.normals[k[near]]  # (m, 3, 2), object frame
        normals.append(np.stack(rotate(poses[near, 2, None], n[..., 0], n[..., 1]), axis=-1))
        rows.append(near)
        fingers.append(np.full(len(near), f))
    if not rows:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 3, 2))
    return np.concatenate(rows), np.concatenate(fingers), np.concatenate(normals)
