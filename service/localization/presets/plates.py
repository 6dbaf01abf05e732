"""Machined plates: a plate on a table, with pockets, holes, bosses, ribs and fillets.

`plate` scatters seeded features over large plains, as on a fixture plate or a housing
lid. `pattern` is a square plate with a symmetric pattern of identical features (four
holes, a bolt circle, a grid of pockets) whose symmetry a single seeded feature breaks (a
chamfered corner, a counterbore, a notch or a pin), so only that feature tells the
symmetric poses apart. Sizes are those of real parts under an 8 mm fingertip: holes
6-20 mm across (some narrower than the tip), pockets 2-6 mm deep, bosses 3-10 mm tall,
fillets and edge rounds of a few millimetres.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from service.localization.presets.classic import SPACING, samples
from service.localization.presets.shapes import (
    Grid,
    Layout,
    circle,
    half_plane,
    raised,
    recessed,
    rounded_box,
    slot,
)
from service.localization.surface import HeightMap

MM = 1e-3


def _body(g: Grid, rng: np.random.Generator) -> tuple[np.ndarray, float, float, dict]:
    """The plate's outline (signed distance), margin to the map edge, thickness, edge style."""
    side = g.side
    margin = rng.uniform(8, 15) * MM
    thick = rng.uniform(8, 20) * MM
    half = side / 2 - margin
    outline = rounded_box(g, side / 2, side / 2, half, half, corner=rng.uniform(1, 10) * MM)
    style = {"edge_r": rng.uniform(0.5, 2.0) * MM, "chamfer": bool(rng.random() < 0.5)}
    return outline, margin, thick, style


def _area_scale(side: float, margin: float) -> float:
    """Feature counts grow with the plate's area (1 for a 170 mm plate)."""
    return ((side - 2 * margin) / 0.17) ** 2


def _count(rng: np.random.Generator, scale: float, lo: float, hi: float) -> int:
    return int(round(scale * rng.uniform(lo, hi)))


def plate(size_units: float = 20.0, seed: int = 0) -> HeightMap:
    """A machined plate with pockets, holes, bosses and ribs, fillets and rounded edges."""
    rng = np.random.default_rng([seed, 101])
    g = Grid.square(samples(size_units), SPACING)
    outline, margin, thick, style = _body(g, rng)
    z = raised(outline, thick, **style)
    layout = Layout(rng, margin + 6 * MM, g.side - margin - 6 * MM, gap=rng.uniform(4, 10) * MM,
                    placed=[])
    scale = _area_scale(g.side, margin)
    up, down = np.zeros_like(z), np.zeros_like(z)
    square = (0.0, np.pi / 2)  # machined features run along the plate's edges
    for _ in range(_count(rng, scale, 1.0, 2.5)):  # milled pockets: flat floors, round corners
        hw, hh = rng.uniform(12, 30) * MM, rng.uniform(10, 22) * MM
        pocket = partial(_pocket, hw=hw, hh=hh, angle=float(rng.choice(square)),
                         corner=rng.uniform(3, 8) * MM, depth=rng.uniform(2, 6) * MM,
                         fillet=rng.uniform(0.5, 2) * MM, rim=rng.uniform(0.3, 1.0) * MM)
        reach = np.hypot(hw, hh) + 1 * MM
        if at := layout.place(reach):
            g.stamp(down, *at, reach, partial(pocket, at=at))
    for _ in range(_count(rng, scale, 2.0, 5.0)):  # drilled holes, blind or through
        r = rng.uniform(3, 10) * MM
        depth = thick if rng.random() < 0.5 else rng.uniform(3 * MM, thick - 1 * MM)
        bore = rng.uniform(3, 6) * MM if rng.random() < 0.3 else 0.0  # a counterbore
        hole = partial(_hole, r=r, depth=depth, rim=rng.uniform(0.3, 1) * MM, bore=bore,
                       bore_depth=rng.uniform(1.5, 3) * MM)
        if at := layout.place(r + bore + 1.5 * MM):
            g.stamp(down, *at, r + bore + 1.5 * MM, partial(hole, at=at))
    for _ in range(_count(rng, scale, 1.0, 3.0)):  # bosses
        r, fillet = rng.uniform(6, 15) * MM, rng.uniform(1, 3) * MM
        boss = partial(_boss, r=r, height=rng.uniform(3, 10) * MM, fillet=fillet,
                       rim=rng.uniform(0.5, 1.5) * MM)
        if at := layout.place(r + fillet):
            g.stamp(up, *at, r + fillet, partial(boss, at=at), np.maximum)
    for _ in range(_count(rng, scale, 0.0, 2.0)):  # ribs
        length, fillet = rng.uniform(40, 100) * MM, rng.uniform(1, 2) * MM
        rib = partial(_rib, length=length, angle=float(rng.choice(square)),
                      half_w=rng.uniform(1.5, 3) * MM, height=rng.uniform(3, 8) * MM,
                      fillet=fillet)
        if at := layout.place(length / 2 + fillet):
            g.stamp(up, *at, length / 2 + fillet, partial(rib, at=at), np.maximum)
    z = z + np.where(outline <= 0, up + down, 0.0)
    return HeightMap(z, SPACING, name=f"plate{size_units:g}-s{seed}")


# Each feature's heights on a (windowed) grid `w`, centred at `at`.

def _pocket(w: Grid, at: tuple[float, float], hw: float, hh: float, angle: float,
            corner: float, depth: float, fillet: float, rim: float) -> np.ndarray:
    """A milled pocket: a rounded rectangle with a fillet round its floor and a rounded rim."""
    outline = rounded_box(w, *at, hw, hh, corner=corner, angle=angle)
    return recessed(outline, depth, fillet=fillet, edge_r=rim)


def _hole(w: Grid, at: tuple[float, float], r: float, depth: float, rim: float, bore: float,
          bore_depth: float) -> np.ndarray:
    """A drilled hole with a chamfered rim, and a counterbore round it when `bore` > 0."""
    hole = recessed(circle(w, *at, r), depth, edge_r=rim, chamfer=True)
    if bore:
        hole = np.minimum(hole, recessed(circle(w, *at, r + bore), bore_depth))
    return hole


def _boss(w: Grid, at: tuple[float, float], r: float, height: float, fillet: float,
          rim: float) -> np.ndarray:
    return raised(circle(w, *at, r), height, fillet=fillet, edge_r=rim)


def _rib(w: Grid, at: tuple[float, float], length: float, angle: float, half_w: float,
         height: float, fillet: float) -> np.ndarray:
    dx, dy = np.cos(angle) * length / 2, np.sin(angle) * length / 2
    outline = slot(w, at[0] - dx, at[1] - dy, at[0] + dx, at[1] + dy, half_w)
    return raised(outline, height, fillet=fillet, edge_r=0.5 * MM)


BREAKERS = ("chamfer", "counterbore", "notch", "pin")


def pattern(size_units: float = 20.0, seed: int = 0) -> HeightMap:
    """A square plate with a symmetric pattern of identical features, broken by one feature."""
    rng = np.random.default_rng([seed, 102])
    g = Grid.square(samples(size_units), SPACING)
    c = g.side / 2
    margin = rng.uniform(8, 15) * MM
    thick = rng.uniform(8, 20) * MM
    inner = c - margin
    outline = rounded_box(g, c, c, inner, inner, corner=1 * MM)
    kind = rng.choice(("holes", "bolt-circle", "pockets"))
    centres: list[tuple[float, float]]
    if kind == "holes":
        a = rng.uniform(0.45, 0.7) * inner
        centres = [(c + sx * a, c + sy * a) for sx in (-1, 1) for sy in (-1, 1)]
        r = rng.uniform(5, 10) * MM
    elif kind == "bolt-circle":
        n = int(rng.choice((4, 6, 8)))
        radius = rng.uniform(0.4, 0.65) * inner
        turn = rng.uniform(0, 2 * np.pi / n)
        centres = [(c + radius * np.cos(turn + 2 * np.pi * k / n),
                    c + radius * np.sin(turn + 2 * np.pi * k / n)) for k in range(n)]
        r = min(rng.uniform(4, 8) * MM, 0.3 * radius * np.sin(np.pi / n))
    else:
        a = rng.uniform(0.45, 0.55) * inner
        centres = [(c + sx * a, c + sy * a) for sx in (-1, 1) for sy in (-1, 1)]
        r = rng.uniform(0.18, 0.3) * inner  # half the side of a square pocket
    depth = thick if (kind != "pockets" and rng.random() < 0.5) else rng.uniform(2, 6) * MM

    def feature(cx: float, cy: float) -> np.ndarray:
        if kind == "pockets":
            return recessed(rounded_box(g, cx, cy, r, r, corner=4 * MM), depth, fillet=1 * MM)
        return recessed(circle(g, cx, cy, r), depth, edge_r=0.5 * MM, chamfer=True)

    features = np.minimum.reduce([feature(*p) for p in centres])
    if kind != "pockets" and rng.random() < 0.5:  # a centre bore, itself symmetric
        features = np.minimum(features, recessed(circle(g, c, c, rng.uniform(0.1, 0.2) * inner),
                                                 rng.uniform(2, 5) * MM, edge_r=0.5 * MM))
    breaker = BREAKERS[int(rng.integers(len(BREAKERS)))]
    corner = rng.integers(4)
    sx, sy = (-1 if corner in (0, 3) else 1), (-1 if corner in (0, 1) else 1)
    if breaker == "chamfer":  # cut one corner of the plate at 45 degrees
        cut = rng.uniform(12, 25) * MM
        tip_x, tip_y = c + sx * inner, c + sy * inner
        outline = np.maximum(outline, half_plane(g, tip_x - sx * cut, tip_y, sx, sy))
    elif breaker == "counterbore":  # one feature of the pattern gets a wider, shallow step
        px, py = centres[int(rng.integers(len(centres)))]
        grow = rng.uniform(4, 7) * MM
        bore = (rounded_box(g, px, py, r + grow, r + grow, corner=4 * MM) if kind == "pockets"
                else circle(g, px, py, r + grow))
        features = np.minimum(features, recessed(bore, rng.uniform(1.5, 3) * MM))
    elif breaker == "notch":  # a rectangular notch in one edge, off its middle
        along = c + rng.choice((-1, 1)) * rng.uniform(0.2, 0.6) * inner
        w, d = rng.uniform(8, 14) * MM, rng.uniform(8, 14) * MM
        edge_at = c + sx * inner
        box = (rounded_box(g, edge_at, along, d, w) if rng.random() < 0.5
               else rounded_box(g, along, edge_at, w, d))
        outline = np.maximum(outline, -box)
    else:  # a dowel pin off the pattern's axes
        pr, pin_h = rng.uniform(3, 5) * MM, rng.uniform(3, 6) * MM
        for _ in range(100):
            px, py = rng.uniform(c - 0.8 * inner, c + 0.8 * inner, size=2)
            if min(np.hypot(px - qx, py - qy) for qx, qy in centres) > r + pr + 8 * MM and \
                    min(abs(px - c), abs(py - c)) > pr + 8 * MM:
                break
        features = features + raised(circle(g, px, py, pr), pin_h, fillet=0.5 * MM,
                                     edge_r=0.5 * MM)
    z = raised(outline, thick, edge_r=0.8 * MM) + np.where(outline <= 0, features, 0.0)
    return HeightMap(z, SPACING, name=f"pattern{size_units:g}-s{seed}")
