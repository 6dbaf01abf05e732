"""Seeded families of planar objects: `NAME[:SEED]` picks one member.

Each preset is a family, not a single shape, so tests and benchmarks can hold members out:
the same seed always gives the same contour. Sizes suit the preset hands (20-30 mm across
the half-width, fingertip radius 8 mm).

* `ellipse` - symmetric under a half turn: no exploration can tell the two poses apart, so
  the honest answer stays "not yet";
* `rounded` - an irregular polygon with rounded corners;
* `blob` - a bumpy star-shaped outline;
* `keyed` - a shape symmetric under a half turn but for one bump: that one feature decides.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from shapely.geometry import Polygon

from service.errors import ObjectError
from service.localization.objects.contour import Contour, make_contour

SAMPLES = 720
"""Vertices of a preset outline (half a degree apart)."""


def _angles() -> np.ndarray:
    return np.linspace(0.0, 2 * np.pi, SAMPLES, endpoint=False)


def _radial(r: np.ndarray, name: str) -> Contour:
    phi = _angles()
    return make_contour(np.column_stack([r * np.cos(phi), r * np.sin(phi)]), name)


def ellipse(seed: int = 0) -> Contour:
    rng = np.random.default_rng([seed, 1])
    a = rng.uniform(0.022, 0.030)
    b = a * rng.uniform(0.55, 0.8)
    phi = _angles()
    return make_contour(np.column_stack([a * np.cos(phi), b * np.sin(phi)]), f"ellipse:{seed}")


def rounded(seed: int = 0) -> Contour:
    """An irregular convex polygon of 3-6 sides whose corners are rounded (radius 4-7 mm)."""
    rng = np.random.default_rng([seed, 2])
    sides = int(rng.integers(3, 7))
    base = 2 * np.pi * np.arange(sides) / sides
    angles = base + rng.uniform(-0.2, 0.2, sides) * 2 * np.pi / sides
    radii = rng.uniform(0.022, 0.030, sides)
    corners = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
    corner = rng.uniform(0.004, 0.007)
    shape = Polygon(corners).convex_hull.buffer(-corner, quad_segs=32).buffer(
        corner, quad_segs=32)
    return make_contour(np.asarray(shape.exterior.coords)[:-1], f"rounded:{seed}")


def blob(seed: int = 0) -> Contour:
    """A star-shaped outline: a few broad lobes plus smaller bumps."""
    rng = np.random.default_rng([seed, 3])
    phi = _angles()
    r = np.ones_like(phi)
    for k in range(2, 10):
        amplitude = rng.uniform(0.3, 1.0) * (0.09 if k < 5 else 0.035)
        r += amplitude * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
    return _radial(0.024 * r, f"blob:{seed}")


def keyed(seed: int = 0) -> Contour:
    """A rounded rectangle or an ellipse (each symmetric under a half turn) with one bump
    3 mm high somewhere on it: only touching the bump tells the two poses apart."""
    rng = np.random.default_rng([seed, 4])
    phi = _angles()
    a = rng.uniform(0.022, 0.028)
    b = a * rng.uniform(0.6, 0.85)
    power = 2.0 if rng.random() < 0.5 else 4.0  # an ellipse or a superellipse
    r = (np.abs(np.cos(phi) / a) ** power + np.abs(np.sin(phi) / b) ** power) ** (-1 / power)
    where = rng.uniform(0, 2 * np.pi)
    gap = np.angle(np.exp(1j * (phi - where)))
    width = 0.006 / r  # about 6 mm of arc (one sd)
    r = r + rng.uniform(0.0025, 0.0035) * np.exp(-0.5 * (gap / width) ** 2)
    return _radial(r, f"keyed:{seed}")


PRESETS: dict[str, Callable[[int], Contour]] = {
    "ellipse": ellipse,
    "rounded": rounded,
    "blob": blob,
    "keyed": keyed,
}
DISAMBIGUATED = ("rounded", "blob", "keyed")
"""Families whose members one feature (or none needed) tells apart from their rotations."""


def preset_object(spec: str) -> Contour:
    """`NAME` or `NAME:SEED`, e.g. `keyed:7`."""
    name, seed = preset_name_and_seed(spec)
    return PRESETS[name](seed)


def preset_name_and_seed(spec: str) -> tuple[str, int]:
    """The family and seed of a preset object's spec, or ObjectError saying what is wrong
    (nothing is built)."""
    name, _, seed_text = spec.partition(":")
    if name not in PRESETS:
        raise ObjectError(f"unknown object '{spec}': presets are "
                          f"{', '.join(PRESETS)} (NAME or NAME:SEED), or a .csv/.stl/.obj/.ply "
                          "file")
    try:
        seed = int(seed_text) if seed_text else 0
    except ValueError:
        raise ObjectError(f"object '{spec}': the seed must be a whole number, e.g. "
                          f"{name}:3") from None
    if seed < 0:
        raise ObjectError(f"object '{spec}': the seed must be >= 0")
    return name, seed
