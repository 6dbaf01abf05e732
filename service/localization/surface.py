"""Height maps and the contact surface a spherical fingertip's centre rides on.

A `HeightMap` is a grid of surface heights (metres) with its sample spacing (metres);
sample [row, col] sits at map coordinates (x, y) = (col * spacing, row * spacing).
The `ContactSurface` is the height the centre of a sphere of radius r reaches over each
point (paper Eq. 7): the grey dilation of the map by the sphere, computed once per map and
radius with scipy.ndimage, after which every hypothesis test is one interpolated lookup.

A map with a single row is a 1-D profile (what a planar finger explores): it is treated as
extruded along y, so lookups ignore y.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from service.errors import MapError
from service.localization.memo import kept

BORDER_ROUNDING = 1e-9
"""Metres a point on the map's border may stray by rounding alone and still be on it: a
pose turned by -180 degrees, not +180, put three readings on the border just off it, and
`grid` weighed a held-out map's exact half-turn image at nothing (declared 180 degrees
off)."""


LARGEST_HEIGHT = 1e9
"""Largest height (in the file's units) a map may hold: a metre in nanometres. A held-out
check's heights near 1e298 overflowed every sum with NumPy's warnings and were advised to be
divided by a million."""


@dataclass(frozen=True, eq=False)
class HeightMap:
    """A validated grid of surface heights in metres."""

    heights: np.ndarray
    spacing: float
    name: str = "map"

    def __post_init__(self) -> None:
        heights = np.asarray(self.heights)
        if heights.ndim == 1:
            heights = heights[np.newaxis, :]
        if heights.ndim != 2:
            raise MapError(
                f"map '{self.name}' has {heights.ndim} dimensions; a height map is a 2-D grid "
                "(or a single row for a profile)"
            )
        if not np.issubdtype(heights.dtype, np.number) or np.iscomplexobj(heights):
            raise MapError(f"map '{self.name}' holds {heights.dtype} values; heights must be real")
        if min(heights.shape) == 0:
            raise MapError(f"map '{self.name}' holds no samples ({heights.shape[0]} rows of "
                           f"{heights.shape[1]}): a height map needs rows of heights")
        if max(heights.shape) < 2:
            raise MapError(
                f"map '{self.name}' is {heights.shape[0]}x{heights.shape[1]} samples; "
                "it needs at least 2 samples along one axis"
            )
        if heights.shape[1] == 1:
            raise MapError(
                f"map '{self.name}' is a single column of {heights.shape[0]} samples; a "
                "profile is a single row: transpose it (one line of a CSV, or "
                "numpy.save(path, heights.T))"
            )
        if not np.all(np.isfinite(heights)):
            bad = int(np.count_nonzero(~np.isfinite(heights)))
            row, col = (int(i) for i in np.argwhere(~np.isfinite(heights))[0])
            raise MapError(
                f"map '{self.name}' has {bad} non-finite height{'s' if bad > 1 else ''} (NaN "
                f"or inf), the first in row {row}, column {col} (counting from 0); fill or "
                "crop them"
            )
        tallest = float(np.max(np.abs(heights)))
        if tallest > LARGEST_HEIGHT:  # no unit makes such heights an object's
            raise MapError(f"map '{self.name}' has heights up to {tallest:.3g}: heights are "
                           "metres, and no unit (millimetres, micrometres) makes that an "
                           "object's; check the file holds heights")
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise MapError(f"map spacing must be a positive number of metres, got {self.spacing}")
        heights = np.ascontiguousarray(heights, dtype=np.float64)
        heights.setflags(write=False)
        object.__setattr__(self, "heights", heights)
        object.__setattr__(self, "spacing", float(self.spacing))

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    @property
    def is_profile(self) -> bool:
        """True for a single-row map: a profile explored by a planar finger."""
        return self.heights.shape[0] == 1

    @property
    def extent(self) -> tuple[float, float]:
        """(x_max, y_max) in metres; the map covers [0, x_max] x [0, y_max]."""
        rows, cols = self.heights.shape
        return ((cols - 1) * self.spacing, (rows - 1) * self.spacing)

    def inside(self, x: np.ndarray, y: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of points inside the map (its border counts), allowing `margin` metres
        beyond it for hypotheses whose positions carry measurement noise."""
        x_max, y_max = self.extent
        margin = margin + BORDER_ROUNDING  # a point on the border, give or take rounding
        x = np.asarray(x)
        mask = (x >= -margin) & (x <= x_max + margin)
        if not self.is_profile:
            y = np.asarray(y)
            mask &= (y >= -margin) & (y <= y_max + margin)
        return mask

    def lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinearly interpolated heights at (x, y) and the inside mask."""
        return _interpolate(self.heights, self.spacing, self.is_profile, x, y), self.inside(x, y)


@dataclass(frozen=True, eq=False)
class ContactSurface:
    """Height of the fingertip centre over each map point, for one map and radius."""

    map: HeightMap
    radius: float
    centre_heights: np.ndarray = field(repr=False)

    def lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre heights at (x, y) (bilinear) and the inside-the-map mask."""
        heights = _interpolate(self.centre_heights, self.map.spacing, self.map.is_profile, x, y)
        return heights, self.map.inside(x, y)

    def height(self, x: float, y: float) -> float:
        """Centre height at one point (for simulators and tests)."""
        return float(self.lookup(np.array([x]), np.array([y]))[0][0])


def _interpolate(
    grid: np.ndarray, spacing: float, is_profile: bool, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    cols = x / spacing
    rows = np.zeros_like(cols) if is_profile else np.asarray(y, dtype=np.float64) / spacing
    coords = np.stack(np.broadcast_arrays(rows, cols)).reshape(2, -1)
    values = ndimage.map_coordinates(grid, coords, order=1, mode="nearest")
    return values.reshape(np.broadcast(rows, cols).shape)


def sphere_structure(radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Footprint (disk) and heights of a sphere cap sampled on the map grid."""
    k = int(np.floor(radius / spacing + 1e-9))
    offsets = np.arange(-k, k + 1) * spacing
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    d2 = dx**2 + dy**2
    footprint = d2 <= radius**2 + 1e-12
    cap = np.sqrt(np.clip(radius**2 - d2, 0.0, None))
    return footprint, np.where(footprint, cap, 0.0)


def sphere_filter(grid: np.ndarray, radius: float, spacing: float, *,
                  erode: bool = False) -> np.ndarray:
    """The grey dilation (or erosion) of `grid` by a sphere of `radius` (edges: nearest); a
    single row is an extruded profile.

    Row by row of the sphere's footprint, as the most (least) over its rows of a 1-D
    dilation of the grid shifted by that row: the same sums and the same result as one 2-D
    `ndimage.grey_dilation`, whose border offsets take memory growing as the footprint's
    side to the fourth power (a 150 mm tip on a 200 mm map at 1 mm needed over 15 GB and
    was killed)."""
    footprint, cap = sphere_structure(radius, spacing)
    if grid.shape[0] == 1:  # a profile: the sphere's extreme over a row lies in its plane
        footprint, cap = footprint[footprint.shape[0] // 2:][:1], cap[cap.shape[0] // 2:][:1]
    k = footprint.shape[0] // 2
    rows = grid.shape[0]
    padded = np.pad(grid, ((k, k), (0, 0)), mode="edge")  # nearest, across rows
    one_d = ndimage.grey_erosion if erode else ndimage.grey_dilation
    pick = np.minimum if erode else np.maximum
    out: np.ndarray | None = None
    for j in range(footprint.shape[0]):
        if not footprint[j].any():
            continue
        # row j of the sphere (symmetric) over the grid j - k rows away
        part = one_d(padded[j:j + rows], footprint=footprint[j][None, :],
                     structure=cap[j][None, :], mode="nearest")
        out = part if out is None else pick(out, part)
    assert out is not None  # the centre row is always in the footprint
    return out


DILATION_WORK_LIMIT = 1e10
"""Most map samples x fingertip footprint samples a contact surface may cost (about a
minute at this machine's 100-500 million per second)."""


def check_radius(height_map: HeightMap, radius: float) -> None:
    """Refuse a fingertip the map cannot take, naming what to change (before any work)."""
    if not (np.isfinite(radius) and radius > 0):
        raise MapError(f"finger radius must be a positive number of metres, got {radius}")
    x_max, y_max = height_map.extent
    shorter = x_max if height_map.is_profile else min(x_max, y_max)
    hint = (f" The radius is in metres: for {radius:g} mm give {radius / 1000:g}." if radius >= 1
            else "")
    if radius > shorter:
        if height_map.is_profile:
            raise MapError(f"finger radius {radius * 1e3:g} mm does not fit on profile "
                           f"'{height_map.name}' ({x_max * 1e3:g} mm long): it must be at most "
                           f"the profile's length.{hint}")
        rows = height_map.heights.shape[0]
        profile = (f" A profile (the planar finger's map) is a single row; this map has "
                   f"{rows}." if rows <= 3 else "")
        raise MapError(f"finger radius {radius * 1e3:g} mm does not fit on map "
                       f"'{height_map.name}' ({x_max * 1e3:g} x {y_max * 1e3:g} mm): it must "
                       f"be at most the map's shorter side ({shorter * 1e3:g} mm).{hint}"
                       f"{profile}")
    k = int(np.floor(radius / height_map.spacing + 1e-9))
    footprint = (2 * k + 1) if height_map.is_profile else (2 * k + 1) ** 2
    if footprint * height_map.heights.size > DILATION_WORK_LIMIT:
        # the spacing at which the work fits, and never finer than a tip needs
        coarser = max(radius / 8, height_map.spacing
                      * (footprint * height_map.heights.size / DILATION_WORK_LIMIT) ** 0.25)
        raise MapError(f"finger radius {radius * 1e3:g} mm spans {2 * k + 1} samples of map "
                       f"'{height_map.name}' ({height_map.shape[1]} x {height_map.shape[0]} "
                       f"samples at {height_map.spacing * 1e3:g} mm): its contact surface "
                       f"would take too long to build; crop the map, or resample it to a "
                       f"spacing of {coarser * 1e3:.3g} mm or coarser.{hint}")


def contact_surface(height_map: HeightMap, radius: float) -> ContactSurface:
    """The centre-height surface for a sphere of `radius` metres, kept while the map lives
    (`memo.kept`)."""
    check_radius(height_map, radius)

    def build() -> ContactSurface:
        dilated = np.ascontiguousarray(sphere_filter(height_map.heights, radius,
                                                     height_map.spacing))
        dilated.setflags(write=False)
        return ContactSurface(map=height_map, radius=float(radius), centre_heights=dilated)

    return kept(height_map, ("contact surface", float(radius)), build)
