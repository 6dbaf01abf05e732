"""The contact model of a planar object: a signed-distance grid of its contour.

A rolling fingertip of radius r touching the object has its centre exactly r outside the
contour: on the contour dilated by r (Eq. 7 in 2-D). One signed-distance grid (positive
outside) serves every tip radius - a centre's residual is its distance minus r - and is
computed once per object, so each hypothesis test is one interpolated lookup, as with height
maps.

The distances are exact, not a raster's: a rasterized distance transform
(scipy.ndimage.distance_transform_edt) is off by up to half a cell, 0.12 mm at the default
0.25 mm cells, about the fingertip's measurement noise; here each grid point's nearest point
on a densely resampled outline is found with a KD-tree and the distance taken to the two
outline pieces beside it. The sign comes from shapely's point-in-polygon test.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.spatial import cKDTree

from service.localization.memo import kept
from service.localization.objects import kernels
from service.localization.objects.contour import Contour

SPACING = 0.00025
"""Grid cell (metres): bilinear lookups of a smooth distance are then exact to ~1 um."""
PAD = 0.03
"""Metres of grid beyond the contour on every side: past any fingertip in contact."""


@dataclass(frozen=True, eq=False)
class ContactField:
    """Signed distance (metres, positive outside) to one contour on a regular grid."""

    contour: Contour
    sdf: np.ndarray = field(repr=False)
    """(rows, cols): rows step along the object's v axis, columns along u."""
    spacing: float
    origin: tuple[float, float]
    """Object-frame (u, v) of sample [0, 0]."""

    @property
    def args(self) -> tuple[np.ndarray, float, float, float]:
        """(grid, spacing, origin u, origin v): what the compiled kernels take."""
        return self.sdf, self.spacing, self.origin[0], self.origin[1]

    def distance(self, u: np.ndarray, v: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance and its gradient (d/du, d/dv) at object-frame points."""
        u = np.asarray(u, dtype=np.float64)
        v = np.broadcast_to(np.asarray(v, dtype=np.float64), u.shape)
        d, gu, gv = kernels.distances(*self.args, np.ascontiguousarray(u.ravel()),
                                      np.ascontiguousarray(v.ravel()))
        return d.reshape(u.shape), gu.reshape(u.shape), gv.reshape(u.shape)


def exact_distance(contour: Contour, u: np.ndarray, v: np.ndarray,
                   resolution: float = 2e-4) -> np.ndarray:
    """Signed distance (positive outside) from points to the contour.

    The outline's samples `resolution` apart find where to look; the distance is then taken
    to the pieces of outline beside the two nearest samples, exact wherever the nearest
    point lies on one of them (everywhere but within a hair of the medial axis).
    """
    dense, _ = contour.resampled(resolution)
    tree = cKDTree(dense)
    query = np.column_stack([np.ravel(u), np.ravel(v)])
    _, near = tree.query(query, k=2)
    best = np.full(len(query), np.inf)
    for idx, offset in ((near[:, 0], -1), (near[:, 0], 0), (near[:, 1], -1), (near[:, 1], 0)):
        a = dense[(idx + offset) % len(dense)]
        b = dense[(idx + offset + 1) % len(dense)]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", query - a, ab)
                    / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
        nearest = a + t[:, None] * ab
        best = np.minimum(best, np.hypot(*(query - nearest).T))
    inside = shapely.contains_xy(contour.polygon, query[:, 0], query[:, 1])
    return np.where(inside, -best, best).reshape(np.shape(u))


def contact_field(contour: Contour, spacing: float = SPACING, pad: float = PAD
                  ) -> ContactField:
    """The signed-distance grid of `contour`, kept while the contour lives (`memo.kept`)."""
    return kept(contour, ("contact field", float(spacing), float(pad)),
                lambda: _grid(contour, spacing, pad))


def _grid(contour: Contour, spacing: float, pad: float) -> ContactField:
    lo = contour.points.min(axis=0) - pad
    hi = contour.points.max(axis=0) + pad
    cols = int(np.ceil((hi[0] - lo[0]) / spacing)) + 1
    rows = int(np.ceil((hi[1] - lo[1]) / spacing)) + 1
    u, v = np.meshgrid(lo[0] + spacing * np.arange(cols), lo[1] + spacing * np.arange(rows))
    sdf = np.ascontiguousarray(exact_distance(contour, u, v))
    sdf.setflags(write=False)
    return ContactField(contour=contour, sdf=sdf, spacing=float(spacing),
                        origin=(float(lo[0]), float(lo[1])))
