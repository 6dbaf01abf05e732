"""Curved shells with small features: a dome, saddle or cylindrical panel seen from above,
with rivet rows, a bead, dimples and a pad a few millimetres across.

The curved base alone is nearly symmetric (a dome looks the same turned about its top);
the small features, most of them narrower than the fingertip, are what tell poses apart.
"""

from __future__ import annotations

import numpy as np

from service.localization.presets.classic import SPACING, samples
from service.localization.presets.shapes import Grid, circle, raised, recessed, rounded_box, slot
from service.localization.surface import HeightMap

MM = 1e-3
KINDS = ("dome", "saddle", "cylinder")


def _cap(g: Grid, cx: float, cy: float, radius: float, height: float) -> np.ndarray:
    """A spherical cap (a rivet head) of base `radius` and `height`."""
    sphere = (radius**2 + height**2) / (2 * height)
    d2 = (g.x - cx) ** 2 + (g.y - cy) ** 2
    return np.where(d2 < radius**2, np.sqrt(np.maximum(sphere**2 - d2, 0)) - (sphere - height), 0)


def shell(size_units: float = 20.0, seed: int = 0) -> HeightMap:
    """A curved panel (dome, saddle or cylinder, chosen by the seed) with small features."""
    rng = np.random.default_rng([seed, 103])
    g = Grid.square(samples(size_units), SPACING)
    side = g.side
    kind = KINDS[int(rng.integers(len(KINDS)))]
    r1 = side * rng.uniform(1.0, 3.0)
    r2 = {"dome": side * rng.uniform(1.0, 3.0), "saddle": -side * rng.uniform(1.2, 3.5),
          "cylinder": np.inf}[kind]
    cx, cy = side * rng.uniform(0.3, 0.7, size=2)
    axis = rng.uniform(0, np.pi)
    u = np.cos(axis) * (g.x - cx) + np.sin(axis) * (g.y - cy)
    v = -np.sin(axis) * (g.x - cx) + np.cos(axis) * (g.y - cy)
    z = -(u**2 / (2 * r1) + v**2 / (2 * r2))
    z = z - z.min()
    up, down = np.zeros_like(z), np.zeros_like(z)
    inset = 10 * MM
    for _ in range(int(rng.integers(1, 3))):  # a row of rivets along a seam
        pitch, angle = rng.uniform(15, 25) * MM, rng.uniform(0, np.pi)
        x0, y0 = rng.uniform(inset, side - inset, size=2)
        rad, height = rng.uniform(2, 4) * MM, rng.uniform(1, 2) * MM
        for k in range(-int(side / pitch), int(side / pitch) + 1):
            px, py = x0 + k * pitch * np.cos(angle), y0 + k * pitch * np.sin(angle)
            if inset < px < side - inset and inset < py < side - inset:
                up = np.maximum(up, _cap(g, px, py, rad, height))
    x0, y0 = rng.uniform(inset, side - inset, size=2)  # a stiffening bead
    length, angle = rng.uniform(0.25, 0.5) * side, rng.uniform(0, np.pi)
    bead_h = rng.uniform(1, 2) * MM
    bead = slot(g, x0, y0, x0 + length * np.cos(angle), y0 + length * np.sin(angle),
                rng.uniform(2, 4) * MM)
    up = np.maximum(up, raised(bead, bead_h, edge_r=bead_h))
    for _ in range(int(rng.integers(1, 4))):  # dimples and small holes
        px, py = rng.uniform(inset, side - inset, size=2)
        down = np.minimum(down, recessed(circle(g, px, py, rng.uniform(3, 8) * MM),
                                         rng.uniform(1, 4) * MM, edge_r=0.5 * MM))
    px, py = rng.uniform(2 * inset, side - 2 * inset, size=2)  # a raised pad (a label)
    pad = rounded_box(g, px, py, rng.uniform(5, 12) * MM, rng.uniform(4, 8) * MM,
                      corner=2 * MM, angle=rng.uniform(0, np.pi))
    up = np.maximum(up, raised(pad, rng.uniform(0.8, 2) * MM, edge_r=0.5 * MM))
    return HeightMap(z + up + down, SPACING, name=f"shell{size_units:g}-s{seed}")
