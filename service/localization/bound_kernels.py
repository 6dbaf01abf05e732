"""Compiled kernels of the certificate (`localizers/certificate.py`): bounds on how well any
pose in a box of poses can fit the readings, from a pyramid of each map block's least and
greatest height and steepest slope.

Every height a bilinear lookup returns lies between the least and the greatest of the four
samples round it, so a reading that may land anywhere in a disk reads a height within the
range of the bilinear cells the disk touches. Blocks of 2^L x 2^L cells (level L) hold
those ranges, so any disk is covered by at most 2 x 2 blocks of one level.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from service.localization.kernels import height_at

_JIT = {"cache": True, "nogil": True}

NEWTON = 40
"""Most steps the search for a box's best height offset takes (it usually needs a few)."""


def pyramid(grid: np.ndarray, spacing: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, steep) of every level, flattened, and each level's (offset, rows, cols):
    level 0 is the map's bilinear cells, each level above joins 2 x 2 blocks of the one
    below. `steep` bounds the gradient's length anywhere in a block."""
    g = np.asarray(grid, dtype=np.float64)
    quads = np.stack([g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]])
    lo, hi = quads.min(axis=0), quads.max(axis=0)
    gx = np.maximum(np.abs(g[:-1, 1:] - g[:-1, :-1]), np.abs(g[1:, 1:] - g[1:, :-1]))
    gy = np.maximum(np.abs(g[1:, :-1] - g[:-1, :-1]), np.abs(g[1:, 1:] - g[:-1, 1:]))
    steep = np.hypot(gx, gy) / spacing
    levels = [(lo, hi, steep)]
    while max(lo.shape) > 1:
        lo, hi, steep = (_halve(lo, np.minimum), _halve(hi, np.maximum),
                         _halve(steep, np.maximum))
        levels.append((lo, hi, steep))
    offsets = np.cumsum([0] + [a.size for a, _, _ in levels])
    index = np.array([(offsets[i], a.shape[0], a.shape[1]) for i, (a, _, _) in
                      enumerate(levels)], dtype=np.int64)
    flat = [np.concatenate([lv[i].ravel() for lv in levels]) for i in range(3)]
    return flat[0], flat[1], flat[2], index


def _halve(a: np.ndarray, join: np.ufunc) -> np.ndarray:
    """Each 2 x 2 block of `a` joined into one (an odd edge repeated)."""
    if a.shape[0] > 1 and a.shape[0] % 2:
        a = np.vstack([a, a[-1:]])
    if a.shape[1] > 1 and a.shape[1] % 2:
        a = np.hstack([a, a[:, -1:]])
    if a.shape[0] > 1:
        a = join(a[0::2], a[1::2])
    if a.shape[1] > 1:
        a = join(a[:, 0::2], a[:, 1::2])
    return a


@numba.njit(**_JIT)
def _disk_range(lo: np.ndarray, hi: np.ndarray, steep: np.ndarray, index: np.ndarray,
                spacing: float, x: float, y: float, radius: float
                ) -> tuple[float, float, float]:
    """Least and greatest height, and steepest slope, a bilinear lookup can return within
    `radius` of (x, y) (clamped to the map, as lookups are)."""
    rows, cols = index[0, 1], index[0, 2]
    i0 = min(max(int(math.floor((y - radius) / spacing)), 0), rows - 1)
    i1 = min(max(int(math.floor((y + radius) / spacing)), 0), rows - 1)
    j0 = min(max(int(math.floor((x - radius) / spacing)), 0), cols - 1)
    j1 = min(max(int(math.floor((x + radius) / spacing)), 0), cols - 1)
    level = 0
    while (i1 >> level) - (i0 >> level) > 1 or (j1 >> level) - (j0 >> level) > 1:
        level += 1
    base, r, c = index[level, 0], index[level, 1], index[level, 2]
    least, most, slope = np.inf, -np.inf, 0.0
    for i in range(i0 >> level, min((i1 >> level) + 1, r)):
        for j in range(j0 >> level, min((j1 >> level) + 1, c)):
            k = base + i * c + j
            least = min(least, lo[k])
            most = max(most, hi[k])
            slope = max(slope, steep[k])
    return least, most, slope


@numba.njit(**_JIT)
def _least_misfit(low: np.ndarray, high: np.ndarray, w: np.ndarray) -> float:
    """A lower bound on min over c of sum_j w_j dist(c, [low_j, high_j])^2: the least
    weighted squared miss of intervals by one shared height offset (convex in c)."""
    a, b = np.min(high), np.max(low)
    if a >= b:
        return 0.0  # one offset lies in every interval
    c1, c2 = a, b  # the slope is <= 0 at a, >= 0 at b
    c = 0.5 * (a + b)
    for _ in range(NEWTON):
        f1 = f2 = 0.0
        for j in range(low.shape[0]):
            if c < low[j]:
                f1 += w[j] * (c - low[j])
                f2 += w[j]
            elif c > high[j]:
                f1 += w[j] * (c - high[j])
                f2 += w[j]
        if f1 == 0.0:
            c1 = c2 = c
            break
        if f1 < 0.0:
            c1 = c
        else:
            c2 = c
        step = c - f1 / f2 if f2 > 0.0 else 0.5 * (c1 + c2)
        c = step if c1 < step < c2 else 0.5 * (c1 + c2)
        if c2 - c1 <= 1e-12:
            break
    # the convex function at its least is above its tangent at c1 anywhere up to c2
    f, g = 0.0, 0.0
    for j in range(low.shape[0]):
        if c1 < low[j]:
            f += w[j] * (c1 - low[j]) ** 2
            g += 2.0 * w[j] * (c1 - low[j])
        elif c1 > high[j]:
            f += w[j] * (c1 - high[j]) ** 2
            g += 2.0 * w[j] * (c1 - high[j])
    return max(f + min(g, 0.0) * (c2 - c1), 0.0)


@numba.njit(**_JIT)
def box_bound(grid: np.ndarray, lo: np.ndarray, hi: np.ndarray, steep: np.ndarray,
              index: np.ndarray, spacing: float, extent: tuple[float, float], margin: float,
              readings: np.ndarray, reach: np.ndarray, x: float, y: float, heading: float,
              half: float, half_turn: float, sd: float, position_sigma: float) -> float:
    """A lower bound on the weighted squared misfit (sum of z^2) of `readings` (K, 3: x, y
    relative to the box's anchor, height) for every pose whose anchor lies within `half`
    (metres, in x and y) of (x, y) and whose heading within `half_turn` of `heading`, the
    height offset free; each reading's sd is `sd` widened by the position noise times the
    steepest slope it may land on. Infinite when a reading lands off the map (past
    `margin`) under every such pose. `reach` (K,) is each reading's distance from the
    anchor."""
    k = readings.shape[0]
    co, si = math.cos(heading), math.sin(heading)
    low, high, w = np.empty(k), np.empty(k), np.empty(k)
    corner = half * math.sqrt(2.0)
    turn = min(half_turn, math.pi)
    x_max, y_max = extent
    for j in range(k):
        px = x + co * readings[j, 0] - si * readings[j, 1]
        py = y + si * readings[j, 0] + co * readings[j, 1]
        radius = corner + reach[j] * turn
        # off the map (past the margin) for every pose in the box: none of them fits
        ox = max(-margin - px, px - (x_max + margin), 0.0)
        oy = max(-margin - py, py - (y_max + margin), 0.0)
        if ox * ox + oy * oy > radius * radius:
            return np.inf
        least, most, slope = _disk_range(lo, hi, steep, index, spacing, px, py, radius)
        # and no further from the centre's height than the steepest slope allows: on
        # smooth ground much tighter than the blocks' range, which overshoot the disk
        centre = height_at(grid, spacing, px, py)
        least = max(least, centre - slope * radius)
        most = min(most, centre + slope * radius)
        low[j], high[j] = least - readings[j, 2], most - readings[j, 2]
        w[j] = 1.0 / (sd * sd + 2.0 * position_sigma**2 * slope * slope)
    return _least_misfit(low, high, w)


@numba.njit(**_JIT)
def search(grid: np.ndarray, lo: np.ndarray, hi: np.ndarray, steep: np.ndarray,
           index: np.ndarray, spacing: float, extent: tuple[float, float], margin: float,
           readings: np.ndarray, reach: np.ndarray, roots: np.ndarray, root_half: float,
           root_half_turn: float, least_half: float, least_half_turn: float, limit: float,
           sd: float, position_sigma: float, skip: np.ndarray, skip_tol: np.ndarray, max_boxes: int,
           max_leaves: int) -> tuple[np.ndarray, int, bool]:
    """Branch and bound over boxes of anchor poses: the boxes (x, y, heading, bound) no
    finer than (`least_half`, `least_half_turn`) that no bound could rule out (bound at
    most `limit`), how many boxes it judged, and whether it finished within `max_boxes`
    and `max_leaves`. Boxes wholly within `skip_tol` of the pose `skip` (the declared
    pose's anchor) are not searched."""
    far = 0.0
    for j in range(reach.shape[0]):
        far = max(far, reach[j])
    stack = np.empty((4096, 5))
    depth = 0
    leaves = np.empty((max_leaves, 4))
    held = 0
    judged = 0
    for r in range(roots.shape[0]):
        stack[depth, 0], stack[depth, 1], stack[depth, 2] = roots[r, 0], roots[r, 1], roots[r, 2]
        stack[depth, 3], stack[depth, 4] = root_half, root_half_turn
        depth += 1
        while depth > 0:
            depth -= 1
            x, y, h = stack[depth, 0], stack[depth, 1], stack[depth, 2]
            half, half_turn = stack[depth, 3], stack[depth, 4]
            dh = abs((h - skip[2] + math.pi) % (2.0 * math.pi) - math.pi)
            if (abs(x - skip[0]) + half <= skip_tol[0] and abs(y - skip[1]) + half <= skip_tol[0]
                    and dh + half_turn <= skip_tol[1]):
                continue
            judged += 1
            if judged > max_boxes:
                return leaves[:held], judged, False
            b = box_bound(grid, lo, hi, steep, index, spacing, extent, margin, readings, reach,
                          x, y, h, half, half_turn, sd, position_sigma)
            if b > limit:
                continue
            fine = half <= least_half
            fine_turn = half_turn <= least_half_turn
            if fine and fine_turn:
                if held == max_leaves:
                    return leaves[:held], judged, False
                leaves[held, 0], leaves[held, 1], leaves[held, 2], leaves[held, 3] = x, y, h, b
                held += 1
                continue
            if depth + 4 > stack.shape[0]:
                grown = np.empty((2 * stack.shape[0], 5))
                grown[:depth] = stack[:depth]
                stack = grown
            # split what blurs the readings most: the turn (times the farthest reading) or
            # the position
            if not fine_turn and (fine or far * half_turn > half * math.sqrt(2.0)):
                q = 0.5 * half_turn
                for sign in (-1.0, 1.0):
                    stack[depth, 0], stack[depth, 1], stack[depth, 2] = x, y, h + sign * q
                    stack[depth, 3], stack[depth, 4] = half, q
                    depth += 1
            else:
                q = 0.5 * half
                for sx in (-1.0, 1.0):
                    for sy in (-1.0, 1.0):
                        stack[depth, 0], stack[depth, 1], stack[depth, 2] = (
                            x + sx * q, y + sy * q, h)
                        stack[depth, 3], stack[depth, 4] = q, half_turn
                        depth += 1
    return leaves[:held], judged, True


_warm = False


def warm_up() -> None:
    """Compile (or load from the disk cache) the certificate's kernels now: its first
    search runs between steps, and compiling there took seconds."""
    global _warm
    if _warm:
        return
    grid = np.zeros((2, 2))
    grid.flags.writeable = False  # contact surfaces are read-only, a type of their own
    lo, hi, steep, index = pyramid(grid, 1.0)
    readings = np.zeros((2, 3))
    search(grid, lo, hi, steep, index, 1.0, (1.0, 1.0), 0.0, readings, np.zeros(2),
           np.zeros((1, 3)), 0.5, 0.1, 0.5, 0.1, 1.0, 1.0, 0.0, np.zeros(3), np.zeros(2), 10, 10)
    _warm = True
