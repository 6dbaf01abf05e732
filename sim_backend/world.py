"""The simulated world: the map, optionally perturbed so it differs from the localizer's map."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.localization.surface import HeightMap


def perturbed(height_map: HeightMap, sigma: float, correlation: float,
              rng: np.random.Generator) -> HeightMap:
    """The map plus smooth noise of std `sigma` metres and about `correlation` metres length."""
    if sigma == 0:
        return height_map
    noise = rng.standard_normal(height_map.shape)
    width = max(correlation / height_map.spacing, 1e-6)
    smooth = ndimage.gaussian_filter(noise, sigma=width if not height_map.is_profile
                                     else (0, width), mode="reflect")
    smooth *= sigma / max(smooth.std(), 1e-300)
    return HeightMap(height_map.heights + smooth, height_map.spacing,
                     name=f"{height_map.name}+perturbation")
