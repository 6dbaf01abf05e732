"""Fractal terrain: a seeded fractional-Brownian surface built by spectral synthesis.

Amplitudes fall as a power of the frequency (the Hurst exponent, drawn from the seed, sets
how rough), phases are random, and the relief grows with the map's size as real terrain's
does. Some seeds also flood the lowest ground to a flat floor (a lake bed or a sanded
basin), so the family has plains as well as rough ground. Synthesis runs on a grid twice
the map's side and is cropped, so the map does not repeat at its edges.
"""

from __future__ import annotations

import numpy as np

from service.localization.presets.classic import SPACING, samples
from service.localization.surface import HeightMap

MM = 1e-3


def fractal(n: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """An n x n fractional-Brownian surface, zero mean, unit range."""
    m = 2 * n
    spectrum = np.fft.rfft2(rng.standard_normal((m, m)))
    fy = np.fft.fftfreq(m)[:, np.newaxis]
    fx = np.fft.rfftfreq(m)[np.newaxis, :]
    f2 = fx**2 + fy**2 + (1.0 / m) ** 2
    z = np.fft.irfft2(spectrum * f2 ** (-(hurst + 1) / 2), s=(m, m))[:n, :n]
    return (z - z.min()) / np.ptp(z)


def terrain(size_units: float = 20.0, seed: int = 0) -> HeightMap:
    """Fractal terrain; the seed draws the roughness, the relief and a possible flat basin."""
    rng = np.random.default_rng([seed, 104])
    n = samples(size_units)
    hurst = rng.uniform(0.5, 0.9)
    relief = rng.uniform(8, 25) * MM * (size_units / 20.0) ** hurst
    z = fractal(n, hurst, rng) * relief
    if rng.random() < 0.5:
        z = np.maximum(z, np.quantile(z, rng.uniform(0.1, 0.3)))
    return HeightMap(z, SPACING, name=f"terrain{size_units:g}-s{seed}")
