"""Where height maps come from: built-in presets by name, or a user's file.

Presets use the paper's convention of 10 samples per map unit with 1 unit = 10 mm.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import ndimage

from service.errors import MapError
from service.localization.surface import HeightMap

UNIT = 0.01
"""One map unit of the paper, in metres."""
SAMPLES_PER_UNIT = 10


def peaks(size_units: float = 20.0) -> HeightMap:
    """MATLAB's `peaks` on [-3, 3]^2, spanning `size_units` (20 in the paper), heights in units."""
    n = int(round(size_units * SAMPLES_PER_UNIT)) + 1
    axis = np.linspace(-3.0, 3.0, n)
    x, y = np.meshgrid(axis, axis)  # x varies along columns, as in MATLAB
    z = (
        3 * (1 - x) ** 2 * np.exp(-(x**2) - (y + 1) ** 2)
        - 10 * (x / 5 - x**3 - y**5) * np.exp(-(x**2) - y**2)
        - 1 / 3 * np.exp(-((x + 1) ** 2) - y**2)
    )
    return HeightMap(z * UNIT, UNIT / SAMPLES_PER_UNIT, name="peaks")


def bumps(size_units: float = 20.0, seed: int = 0, amplitude_units: float = 2.0,
          width_units: float = 1.5) -> HeightMap:
    """Seeded smooth random bumps: white noise low-passed to bumps about `width_units` wide."""
    n = int(round(size_units * SAMPLES_PER_UNIT)) + 1
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, n))
    smooth = ndimage.gaussian_filter(noise, sigma=width_units * SAMPLES_PER_UNIT, mode="reflect")
    smooth *= amplitude_units / smooth.std()
    return HeightMap(smooth * UNIT, UNIT / SAMPLES_PER_UNIT, name=f"bumps{size_units:g}-s{seed}")


def eggcrate(size_units: float = 20.0, period_units: float = 4.0,
             amplitude_units: float = 1.0) -> HeightMap:
    """A periodic egg-crate: every period looks the same, so a pose is genuinely ambiguous."""
    n = int(round(size_units * SAMPLES_PER_UNIT)) + 1
    axis = np.linspace(0.0, size_units, n)
    x, y = np.meshgrid(axis, axis)
    k = 2 * np.pi / period_units
    z = amplitude_units * np.sin(k * x) * np.sin(k * y)
    return HeightMap(z * UNIT, UNIT / SAMPLES_PER_UNIT, name="eggcrate")


PRESETS: dict[str, Callable[[], HeightMap]] = {
    "peaks": peaks,
    "bumps": bumps,
    "eggcrate": eggcrate,
}


def preset(spec: str) -> HeightMap:
    """A preset by name; `bumps:SIZE[:SEED]` and `peaks:SIZE` choose size in units (and seed)."""
    name, *args = spec.split(":")
    if name not in PRESETS:
        raise MapError(f"unknown map preset '{name}'; presets are {', '.join(sorted(PRESETS))}")
    try:
        numbers = [float(a) for a in args]
    except ValueError:
        raise MapError(
            f"map preset '{spec}': size and seed must be numbers, e.g. bumps:40:3") from None
    if numbers and not (2 <= numbers[0] <= 400):
        raise MapError(f"map preset '{spec}': size must be 2..400 units")
    if name == "bumps" and len(numbers) >= 2:
        return bumps(numbers[0], seed=int(numbers[1]))
    if len(numbers) > 1:
        raise MapError(f"map preset '{spec}' takes at most a size")
    return PRESETS[name](*numbers)


def load_map(spec: str, spacing: float | None = None) -> HeightMap:
    """A preset name, or a `.npy` / `.csv` / `.txt` grid of heights in metres with `spacing`."""
    path = Path(spec)
    if path.suffix.lower() not in {".npy", ".csv", ".txt"}:
        if spacing is not None:
            raise MapError("--spacing applies to map files, not presets")
        return preset(spec)
    if spacing is None:
        raise MapError(f"map file '{spec}' needs --spacing (metres between samples)")
    if not path.is_file():
        raise MapError(f"map file '{spec}' does not exist")
    try:
        if path.suffix.lower() == ".npy":
            heights = np.load(path, allow_pickle=False)
        else:
            delimiter = "," if path.suffix.lower() == ".csv" else None
            heights = np.loadtxt(path, delimiter=delimiter, ndmin=2)
    except (ValueError, OSError, EOFError) as exc:
        raise MapError(f"map file '{spec}' could not be read: {exc}".splitlines()[0]) from None
    return HeightMap(heights, spacing, name=path.stem)
