"""1-D profiles, what a planar finger explores: smooth random ones, or a row cut from a surface.

A cut takes a row from the middle 80 % of the surface with the most detail (the top third
by total curvature, one drawn by the seed), so it crosses features rather than running
along a plain or a featureless curve.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.localization.presets.classic import SAMPLES_PER_UNIT, SPACING, UNIT, samples
from service.localization.surface import HeightMap


def smooth_profile(size_units: float = 20.0, seed: int = 0) -> HeightMap:
    """Seeded smooth random bumps along a line; their width and height drawn by the seed."""
    rng = np.random.default_rng([seed, 105])
    width, amplitude = rng.uniform(0.8, 2.0), rng.uniform(1.0, 2.0)
    z = ndimage.gaussian_filter1d(rng.standard_normal(samples(size_units)),
                                  sigma=width * SAMPLES_PER_UNIT, mode="reflect")
    z *= amplitude * UNIT / z.std()
    return HeightMap(z[np.newaxis, :], SPACING, name=f"profile-smooth{size_units:g}-s{seed}")


def cut(surface: HeightMap, seed: int = 0) -> HeightMap:
    """A single row of `surface`, chosen by the seed among its most varied rows."""
    heights = surface.heights
    if surface.is_profile:
        return surface
    rows = heights.shape[0]
    lo, hi = int(0.1 * rows), max(int(0.9 * rows), int(0.1 * rows) + 1)
    detail = np.abs(np.diff(heights[lo:hi], n=2, axis=1)).sum(axis=1)
    varied = lo + np.flatnonzero(detail >= np.quantile(detail, 2 / 3))
    row = int(np.random.default_rng([seed, 106]).choice(varied))
    return HeightMap(heights[row:row + 1].copy(), surface.spacing,
                     name=f"profile-{surface.name}-row{row}")
