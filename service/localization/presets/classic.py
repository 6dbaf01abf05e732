"""The benchmark surfaces of the paper and BENCHMARKS.md: `peaks`, `bumps`, `eggcrate`.

Presets use the paper's convention of 10 samples per map unit with 1 unit = 10 mm, so
every preset is sampled at 1 mm.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.localization.surface import HeightMap

UNIT = 0.01
"""One map unit of the paper, in metres."""
SAMPLES_PER_UNIT = 10
SPACING = UNIT / SAMPLES_PER_UNIT
"""Sample spacing of every preset (1 mm)."""


def samples(size_units: float) -> int:
    """Samples along a side `size_units` long."""
    return int(round(size_units * SAMPLES_PER_UNIT)) + 1


def peaks(size_units: float = 20.0) -> HeightMap:
    """MATLAB's `peaks` on [-3, 3]^2, spanning `size_units` (20 in the paper), heights in units."""
    axis = np.linspace(-3.0, 3.0, samples(size_units))
    x, y = np.meshgrid(axis, axis)  # x varies along columns, as in MATLAB
    z = (
        3 * (1 - x) ** 2 * np.exp(-(x**2) - (y + 1) ** 2)
        - 10 * (x / 5 - x**3 - y**5) * np.exp(-(x**2) - y**2)
        - 1 / 3 * np.exp(-((x + 1) ** 2) - y**2)
    )
    return HeightMap(z * UNIT, SPACING, name="peaks")


def bumps(size_units: float = 20.0, seed: int = 0, amplitude_units: float = 2.0,
          width_units: float = 1.5) -> HeightMap:
    """Seeded smooth random bumps: white noise low-passed to bumps about `width_units` wide."""
    n = samples(size_units)
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, n))
    smooth = ndimage.gaussian_filter(noise, sigma=width_units * SAMPLES_PER_UNIT, mode="reflect")
    smooth *= amplitude_units / smooth.std()
    return HeightMap(smooth * UNIT, SPACING, name=f"bumps{size_units:g}-s{seed}")


def eggcrate(size_units: float = 20.0, period_units: float = 4.0,
             amplitude_units: float = 1.0) -> HeightMap:
    """A periodic egg-crate: every period looks the same, so a pose is genuinely ambiguous."""
    axis = np.linspace(0.0, size_units, samples(size_units))
    x, y = np.meshgrid(axis, axis)
    k = 2 * np.pi / period_units
    z = amplitude_units * np.sin(k * x) * np.sin(k * y)
    return HeightMap(z * UNIT, SPACING, name="eggcrate")
