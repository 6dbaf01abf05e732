"""Machined shapes as signed distances, and the height profiles cut around their edges.

A feature is its outline as a signed distance field on the map grid (metres; negative
inside), so a fillet, a rounded or a chamfered edge is one formula of that distance
whatever the outline: circle, rounded rectangle, slot. Outlines combine as the max
(intersection) or min (union) of their distances.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """Sample coordinates of a square map: x along columns, y along rows (metres)."""

    x: np.ndarray
    y: np.ndarray

    @classmethod
    def square(cls, samples: int, spacing: float) -> Grid:
        axis = np.arange(samples) * spacing
        x, y = np.meshgrid(axis, axis)
        return cls(x, y)

    @property
    def side(self) -> float:
        return float(self.x[0, -1])

    def window(self, cx: float, cy: float, reach: float) -> tuple[Grid, tuple[slice, slice]]:
        """The part of the grid within `reach` of (cx, cy), and where it sits in the whole."""
        spacing = float(self.x[0, 1] - self.x[0, 0])
        rows, cols = self.x.shape
        c0, c1 = int((cx - reach) / spacing) - 1, int((cx + reach) / spacing) + 2
        r0, r1 = int((cy - reach) / spacing) - 1, int((cy + reach) / spacing) + 2
        where = (slice(max(r0, 0), min(r1, rows)), slice(max(c0, 0), min(c1, cols)))
        return Grid(self.x[where], self.y[where]), where

    def stamp(self, target: np.ndarray, cx: float, cy: float, reach: float,
              shape: Callable[[Grid], np.ndarray], combine: Callable = np.minimum) -> None:
        """Combine a feature reaching no further than `reach` from (cx, cy) into `target`,
        computing it only near its centre."""
        sub, where = self.window(cx, cy, reach)
        target[where] = combine(target[where], shape(sub))


def circle(g: Grid, cx: float, cy: float, radius: float) -> np.ndarray:
    return np.hypot(g.x - cx, g.y - cy) - radius


def rounded_box(g: Grid, cx: float, cy: float, half_w: float, half_h: float,
                corner: float = 0.0, angle: float = 0.0) -> np.ndarray:
    """A rectangle centred at (cx, cy), turned by `angle`, with corners of radius `corner`."""
    c, s = np.cos(angle), np.sin(angle)
    u = np.abs(c * (g.x - cx) + s * (g.y - cy)) - (half_w - corner)
    v = np.abs(-s * (g.x - cx) + c * (g.y - cy)) - (half_h - corner)
    outside = np.hypot(np.maximum(u, 0.0), np.maximum(v, 0.0))
    return outside + np.minimum(np.maximum(u, v), 0.0) - corner


def slot(g: Grid, x0: float, y0: float, x1: float, y1: float, radius: float) -> np.ndarray:
    """A slot (stadium) of `radius` around the segment from (x0, y0) to (x1, y1)."""
    dx, dy = x1 - x0, y1 - y0
    t = np.clip(((g.x - x0) * dx + (g.y - y0) * dy) / max(dx * dx + dy * dy, 1e-18), 0, 1)
    return np.hypot(g.x - (x0 + t * dx), g.y - (y0 + t * dy)) - radius


def half_plane(g: Grid, px: float, py: float, nx: float, ny: float) -> np.ndarray:
    """Signed distance to the line through (px, py); positive on the side `(nx, ny)` points to."""
    n = np.hypot(nx, ny)
    return ((g.x - px) * nx + (g.y - py) * ny) / n


def quarter(d: np.ndarray, r: float) -> np.ndarray:
    """Height lost at distance `d` from an edge rounded to radius `r` (r at d = 0, 0 from d = r).

    The same quarter circle is a convex round on a top edge and a concave fillet at the
    foot of a wall.
    """
    if r <= 0:
        return np.zeros_like(d)
    t = np.clip(r - d, 0.0, r)
    return r - np.sqrt(np.maximum(r * r - t * t, 0.0))


def edge(d: np.ndarray, r: float, chamfer: bool) -> np.ndarray:
    """Height lost at distance `d` inside a top edge: a 45-degree chamfer or a round."""
    return np.clip(r - d, 0.0, r) if chamfer else quarter(d, r)


def raised(sd: np.ndarray, height: float, fillet: float = 0.0, edge_r: float = 0.0,
           chamfer: bool = False) -> np.ndarray:
    """Height above the base of a boss or rib of outline `sd`: a rounded (or chamfered) top
    edge inside, a fillet at its foot outside, zero beyond."""
    fillet, edge_r = min(fillet, height), min(edge_r, height - min(fillet, height))
    inside = height - edge(-sd, edge_r, chamfer)
    return np.where(sd <= 0, inside, np.minimum(quarter(sd, fillet), height))


def recessed(sd: np.ndarray, depth: float, fillet: float = 0.0, edge_r: float = 0.0,
             chamfer: bool = False) -> np.ndarray:
    """Height (negative) of a pocket or hole of outline `sd`: a fillet round its floor
    inside, a rounded (or chamfered) rim outside, zero beyond."""
    fillet, edge_r = min(fillet, depth), min(edge_r, depth - min(fillet, depth))
    inside = -depth + quarter(-sd, fillet)
    return np.where(sd <= 0, inside, -edge(sd, edge_r, chamfer))


@dataclass
class Layout:
    """Places round footprints on a region without overlap (a seeded rejection sampler)."""

    rng: np.random.Generator
    lo: float
    hi: float
    gap: float
    placed: list[tuple[float, float, float]]

    def place(self, reach: float, tries: int = 200) -> tuple[float, float] | None:
        """A centre whose circle of `reach` fits inside [lo, hi]^2 and clears every other."""
        lo, hi = self.lo + reach, self.hi - reach
        if hi <= lo:
            return None
        for _ in range(tries):
            cx, cy = self.rng.uniform(lo, hi, size=2)
            if all(np.hypot(cx - px, cy - py) >= reach + pr + self.gap
                   for px, py, pr in self.placed):
                self.placed.append((float(cx), float(cy), reach))
                return float(cx), float(cy)
        return None
