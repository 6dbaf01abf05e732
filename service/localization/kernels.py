"""Compiled inner loops over hypotheses x readings, shared by localizers and policies (numba).

Why compiled: an update of a sampled localizer is a dozen passes over a few hundred poses
x a few dozen readings. In numpy each pass is 20-50 array operations, and at that size
each operation's fixed cost outweighs its arithmetic: a 16-pose Gauss-Newton step took
0.2 ms, nearly all of it overhead (BENCHMARKS.md B3). Here each pass is one loop, and the
bilinear lookup every pass shares is written once (`_bilinear`).

The functions take raw arrays, not objects: `localizers/fitting.py` wraps the surface
ones for the rest of the code; `localizers/pool.niche`, `localizers/convergence.distinct`
and `policies/info_gain.information` call the others. They are compiled on first use and
cached on disk (`cache=True`), so only the first run on a machine pays the compile;
`warm_up` does it ahead of time for callers with a deadline (the daemon, benchmarks).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from service.localization.surface import BORDER_ROUNDING

_JIT = {"cache": True, "nogil": True}

EDGE_STEP_SLACK = 0.1
"""How far (in step lengths) a blocked step's target may lie inside the map's edge and
still have been stopped by it: the step's length and direction noise."""


@numba.njit(inline="always", **_JIT)
def _locate(size: int, spacing: float, v: float) -> tuple[int, float]:
    """The sample at or below `v` along an axis of `size` samples (clamped at the edge) and
    the fraction of the way to the next."""
    f = min(max(v / spacing, 0.0), size - 1.0)
    i = min(int(f), size - 2)
    return i, f - i


@numba.njit(**_JIT)
def _bilinear(grid: np.ndarray, spacing: float, x: float, y: float
              ) -> tuple[float, float, float]:
    """Height and gradient (d/dx, d/dy) at (x, y), clamped at the edge; a one-row grid is
    a profile along x."""
    rows, cols = grid.shape
    ix, tx = _locate(cols, spacing, x)
    if rows == 1:
        v0, v1 = grid[0, ix], grid[0, ix + 1]
        return v0 + tx * (v1 - v0), (v1 - v0) / spacing, 0.0
    iy, ty = _locate(rows, spacing, y)
    v00, v01 = grid[iy, ix], grid[iy, ix + 1]
    v10, v11 = grid[iy + 1, ix], grid[iy + 1, ix + 1]
    top = v00 + tx * (v01 - v00)
    bottom = v10 + tx * (v11 - v10)
    gx = ((1 - ty) * (v01 - v00) + ty * (v11 - v10)) / spacing
    return top + ty * (bottom - top), gx, (bottom - top) / spacing


@numba.njit(inline="always", **_JIT)
def _height(grid: np.ndarray, spacing: float, x: float, y: float) -> float:
    """`_bilinear`'s height alone, bit for bit: the screens' inner loops never need the
    gradient, and computing it cost the sweep a quarter of its time."""
    rows, cols = grid.shape
    ix, tx = _locate(cols, spacing, x)
    if rows == 1:
        return grid[0, ix] + tx * (grid[0, ix + 1] - grid[0, ix])
    iy, ty = _locate(rows, spacing, y)
    top = grid[iy, ix] + tx * (grid[iy, ix + 1] - grid[iy, ix])
    bottom = grid[iy + 1, ix] + tx * (grid[iy + 1, ix + 1] - grid[iy + 1, ix])
    return top + ty * (bottom - top)


height_at = _height
"""`_height` for other kernel modules: one bilinear lookup, clamped at the edge."""


@numba.njit(**_JIT)
def sample(grid: np.ndarray, spacing: float, x: np.ndarray, y: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_bilinear` at every point of the flat arrays `x`, `y`."""
    n = x.shape[0]
    value, gx, gy = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        value[i], gx[i], gy[i] = _bilinear(grid, spacing, x[i], y[i])
    return value, gx, gy


@numba.njit(**_JIT)
def _inside(x: float, y: float, extent: tuple[float, float], profile: bool,
            margin: float) -> bool:
    m = margin + BORDER_ROUNDING
    on_x = -m <= x <= extent[0] + m
    return on_x if profile else on_x and -m <= y <= extent[1] + m


@numba.njit(**_JIT)
def _edge_explains(x0: float, y0: float, c: float, s: float, row: np.ndarray,
                   extent: tuple[float, float], profile: bool, margin: float) -> bool:
    """Whether a pose explains reading `row`'s blocked step, if it was one (columns 3-4
    hold its command): the target must lie off the map, give or take `margin` plus a
    tenth of the step (the step's own length and direction noise)."""
    if row.shape[0] < 5 or (row[3] == 0.0 and row[4] == 0.0):
        return True
    tx, ty = row[0] + row[3], row[1] + row[4]
    slack = margin + EDGE_STEP_SLACK * math.hypot(row[3], row[4])
    return not _inside(x0 + c * tx - s * ty, y0 + s * tx + c * ty, extent, profile, -slack)


@numba.njit(**_JIT)
def relative_residuals(grid: np.ndarray, spacing: float, extent: tuple[float, float],
                       profile: bool, poses: np.ndarray, readings: np.ndarray, margin: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, K) of `readings` (K, 3 or 5) against each start pose, heights
    relative to the pose's own first contact, and whether each reading lies on the map
    (and a blocked step's target off it: `_edge_explains`)."""
    n, k = poses.shape[0], readings.shape[0]
    resid = np.empty((n, k))
    on_map = np.empty((n, k), dtype=np.bool_)
    for i in range(n):
        px, py = poses[i, 0], poses[i, 1]
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        z0 = _height(grid, spacing, px, py)
        for j in range(k):
            x = px + c * readings[j, 0] - s * readings[j, 1]
            y = py + s * readings[j, 0] + c * readings[j, 1]
            resid[i, j] = _height(grid, spacing, x, y) - z0 - readings[j, 2]
            on_map[i, j] = (_inside(x, y, extent, profile, margin)
                            and _edge_explains(px, py, c, s, readings[j], extent, profile,
                                               margin))
    return resid, on_map


@numba.njit(**_JIT)
def offset_residuals(grid: np.ndarray, spacing: float, extent: tuple[float, float],
                     profile: bool, poses: np.ndarray, history: np.ndarray, margin: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, K) of every reading, first contact included, with the height offset
    between hand and map fitted (their mean removed) per pose."""
    n, k = poses.shape[0], history.shape[0]
    resid = np.empty((n, k))
    on_map = np.empty((n, k), dtype=np.bool_)
    for i in range(n):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        total = 0.0
        for j in range(k):
            x = poses[i, 0] + c * history[j, 0] - s * history[j, 1]
            y = poses[i, 1] + s * history[j, 0] + c * history[j, 1]
            resid[i, j] = _height(grid, spacing, x, y) - history[j, 2]
            on_map[i, j] = (_inside(x, y, extent, profile, margin)
                            and _edge_explains(poses[i, 0], poses[i, 1], c, s, history[j],
                                               extent, profile, margin))
            total += resid[i, j]
        mean = total / k
        for j in range(k):
            resid[i, j] -= mean
    return resid, on_map


@numba.njit(**_JIT)
def heights_and_jacobian(grid: np.ndarray, spacing: float, pose: np.ndarray,
                         history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For one start pose (3,): the map's centre height under each reading (K,) and its
    derivatives by (x0, y0, heading) (K, 3), for the least-squares refinement."""
    k = history.shape[0]
    heights = np.empty(k)
    jac = np.empty((k, 3))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    for j in range(k):
        dx, dy = history[j, 0], history[j, 1]
        z, gx, gy = _bilinear(grid, spacing, pose[0] + c * dx - s * dy,
                              pose[1] + s * dx + c * dy)
        heights[j] = z
        jac[j, 0], jac[j, 1] = gx, gy
        jac[j, 2] = gx * (-s * dx - c * dy) + gy * (c * dx - s * dy)
    return heights, jac


@numba.njit(**_JIT)
def slope_squares(grid: np.ndarray, spacing: float, poses: np.ndarray, history: np.ndarray
                  ) -> np.ndarray:
    """For every start pose (N, 3): the squared slope of the map under each reading (N, K),
    the term `refine.reading_sigmas` turns position noise into height noise with."""
    n, k = poses.shape[0], history.shape[0]
    out = np.empty((n, k))
    for i in range(n):
        _, jac = heights_and_jacobian(grid, spacing, poses[i], history)
        for j in range(k):
            out[i, j] = jac[j, 0]**2 + jac[j, 1]**2
    return out


@numba.njit(**_JIT)
def log_likelihood(resid: np.ndarray, on_map: np.ndarray, sigma: np.ndarray,
                   outlier_probability: float, outlier_range: float) -> np.ndarray:
    """Per row, the sum over readings of log(a exp(-z^2 / 2) + b), a Gaussian (sd `sigma`,
    (K,)) plus a uniform outlier floor b; an off-map reading scores -1000.

    Far from the crossover of its two terms one of them is below 1e-16 of the other, and
    the log is that of the larger alone, log a - z^2 / 2 or log b: no exp and no log
    (most of the cost) for a reading a hypothesis plainly misses, or without outliers.
    """
    n, k = resid.shape
    floor = outlier_probability / outlier_range + 1e-300
    log_floor = math.log(floor)
    log_peak = np.empty(k)
    for j in range(k):
        log_peak[j] = math.log((1 - outlier_probability) / sigma[j])
    out = np.zeros(n)
    for i in range(n):
        total = 0.0
        for j in range(k):
            if not on_map[i, j]:
                total -= 1e3
                continue
            z = resid[i, j] / sigma[j]
            gaussian = log_peak[j] - 0.5 * z * z
            if gaussian > log_floor + 37.0:
                total += gaussian
            elif gaussian < log_floor - 37.0:
                total += log_floor
            else:
                total += math.log(math.exp(gaussian) + floor)
        out[i] = total
    return out


@numba.njit(**_JIT)
def gauss_newton(grid: np.ndarray, spacing: float, poses: np.ndarray, history: np.ndarray,
                 weights: np.ndarray, iterations: int, damping: float, max_move: float,
                 lever: float, profile: bool, extent: tuple[float, float]) -> np.ndarray:
    """Damped Gauss-Newton steps on (x0, y0, heading) per pose, the height offset
    eliminated; a step is capped at `max_move` metres (and max_move / lever radians);
    max_move <= 0 leaves it uncapped. On a profile only x0 moves: y0 means nothing there
    and the direction is one of two, not a continuum. A step never carries a reading
    further past the map's edge (`extent`) than the pose had it: it is halved until it
    does not, or not taken (the truth refitted freely put a far reading a millimetre past
    the edge, and was then ruled out as off the map). See `fitting.gauss_newton`."""
    n, k = poses.shape[0], history.shape[0]
    w = weights / weights.sum()
    out = poses.copy()
    jac = np.empty((4, k))  # d/dx, d/dy, d/dheading, and the height residual
    normal = np.empty((3, 4))  # [A | b] of the normal equations
    for i in range(n):
        past = _past_edge(out[i, 0], out[i, 1], out[i, 2], history, extent, profile)
        for _ in range(iterations):
            c, s = math.cos(out[i, 2]), math.sin(out[i, 2])
            for j in range(k):
                dx, dy = history[j, 0], history[j, 1]
                z, gx, gy = _bilinear(grid, spacing, out[i, 0] + c * dx - s * dy,
                                      out[i, 1] + s * dx + c * dy)
                jac[0, j], jac[1, j] = gx, gy
                jac[2, j] = gx * (-s * dx - c * dy) + gy * (c * dx - s * dy)
                jac[3, j] = z - history[j, 2]
            for r in range(4):  # centre every column: the free offset, eliminated
                mean = 0.0
                for j in range(k):
                    mean += jac[r, j] * w[j]
                for j in range(k):
                    jac[r, j] -= mean
            for a in range(3):
                for b in range(a, 4):
                    acc = 0.0
                    for j in range(k):
                        acc += jac[a, j] * jac[b, j] * w[j]
                    normal[a, b] = acc
                    if b < 3:
                        normal[b, a] = acc
            bump = damping * (1.0 + normal[0, 0] + normal[1, 1] + normal[2, 2]) / 3
            for a in range(3):
                normal[a, a] += bump
            if profile:
                sx, sy, sh = normal[0, 3] / normal[0, 0], 0.0, 0.0
            else:
                sx, sy, sh = _solved3(normal)
            if max_move > 0:
                scale = max(math.hypot(sx, sy) / max_move, abs(sh) * lever / max_move, 1.0)
                sx, sy, sh = sx / scale, sy / scale, sh / scale
            for _halving in range(6):
                after = _past_edge(out[i, 0] - sx, out[i, 1] - sy, out[i, 2] - sh, history,
                                   extent, profile)
                if after <= past + 1e-12:
                    break
                sx, sy, sh = 0.5 * sx, 0.5 * sy, 0.5 * sh
            else:
                break  # no step along this way keeps the readings where they were
            past = after
            out[i, 0] -= sx
            out[i, 1] -= sy
            out[i, 2] -= sh
        out[i, 2] = (out[i, 2] + math.pi) % (2 * math.pi) - math.pi
    return out


@numba.njit(inline="always", **_JIT)
def _past_edge(x0: float, y0: float, heading: float, history: np.ndarray,
               extent: tuple[float, float], profile: bool) -> float:
    """How far (metres) the reading furthest past the map's edge lies under a pose (0 if
    every reading is on the map)."""
    c, s = math.cos(heading), math.sin(heading)
    worst = 0.0
    for j in range(history.shape[0]):
        x = x0 + c * history[j, 0] - s * history[j, 1]
        out = max(-x, x - extent[0])
        if not profile:
            y = y0 + s * history[j, 0] + c * history[j, 1]
            out = max(out, -y, y - extent[1])
        worst = max(worst, out)
    return worst


@numba.njit(**_JIT)
def _solve3(m: np.ndarray) -> np.ndarray:
    """Solve the symmetric 3 x 3 system m[:, :3] x = m[:, 3] by Cramer's rule."""
    x0, x1, x2 = _solved3(m)
    return np.array([x0, x1, x2])


@numba.njit(inline="always", **_JIT)
def _solved3(m: np.ndarray) -> tuple[float, float, float]:
    """`_solve3` as three numbers: no array to allocate in an inner loop."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    if abs(det) <= 1e-300:
        det = 1e-300
    c11 = m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]
    c12 = m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]
    c22 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    b0, b1, b2 = m[0, 3], m[1, 3], m[2, 3]
    return ((c00 * b0 + c01 * b1 + c02 * b2) / det, (c01 * b0 + c11 * b1 + c12 * b2) / det,
            (c02 * b0 + c12 * b1 + c22 * b2) / det)


@numba.njit(**_JIT)
def first_of_each_mode(poses: np.ndarray, position_tol: float, heading_tol: float
                       ) -> np.ndarray:
    """Mask of the poses (N, 3), given best first, that are not within tolerance of a
    better pose already kept: greedy suppression, O(N x kept)."""
    n = poses.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    kept = np.empty(n, dtype=np.intp)
    count = 0
    for i in range(n):
        alone = True
        for m in range(count):
            j = kept[m]
            turn = (poses[i, 2] - poses[j, 2] + math.pi) % (2 * math.pi) - math.pi
            if (math.hypot(poses[i, 0] - poses[j, 0], poses[i, 1] - poses[j, 1])
                    <= position_tol and abs(turn) <= heading_tol):
                alone = False
                break
        if alone:
            keep[i] = True
            kept[count] = i
            count += 1
    return keep


_warm = False


@numba.njit(**_JIT)
def best_per_key(keys: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Mask of the best-scoring entry for each distinct key (ties: the lowest index), in
    one pass over an open-addressing hash table: O(N), where sorting took two sorts."""
    n = keys.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    slot_key = np.empty(size, dtype=np.int64)
    slot_of = np.full(size, -1, dtype=np.intp)
    for i in range(n):
        h = (np.uint64(keys[i]) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)
        slot = np.intp(h) & (size - 1)
        while slot_of[slot] >= 0 and slot_key[slot] != keys[i]:
            slot = (slot + 1) & (size - 1)
        if slot_of[slot] < 0:
            slot_key[slot], slot_of[slot] = keys[i], i
        elif score[i] > score[slot_of[slot]]:
            slot_of[slot] = i
    best = np.zeros(n, dtype=np.bool_)
    for slot in range(size):
        if slot_of[slot] >= 0:
            best[slot_of[slot]] = True
    return best


@numba.njit(**_JIT)
def information(readings: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    """Per option, -sum_i w_i log sum_j w_j exp(-|z_i - z_j|^2 / (4 sigma^2)) over the
    readings (options, N, D) that N weighted hypotheses predict (see
    `policies.info_gain.information`). Each pair is visited once (the kernel is
    symmetric), and pairs more than sqrt(40) apart add exp(-40) or less: skipped."""
    options, n, d = readings.shape
    scale = 1.0 / (4 * sigma * sigma)
    out = np.zeros(options)
    density = np.empty(n)
    for o in range(options):
        for i in range(n):
            density[i] = weights[i]  # the pair (i, i)
        for i in range(n):
            for j in range(i + 1, n):
                d2 = 0.0
                for k in range(d):
                    diff = readings[o, i, k] - readings[o, j, k]
                    d2 += diff * diff
                d2 *= scale
                if d2 < 40.0:
                    e = math.exp(-d2)
                    density[i] += weights[j] * e
                    density[j] += weights[i] * e
        total = 0.0
        for i in range(n):
            total -= weights[i] * math.log(max(density[i], 1e-300))
        out[o] = total
    return out


TILE = 8
"""Positions per side of a sweep tile (`sweep_screen`)."""


@numba.njit(**_JIT)
def _block(grid: np.ndarray, block: float, x: float, y: float) -> float:
    """The value of the block (`block` metres a side) holding (x, y), clamped at the edge."""
    rows, cols = grid.shape
    ix = min(max(int(x / block), 0), cols - 1)
    iy = 0 if rows == 1 else min(max(int(y / block), 0), rows - 1)
    return grid[iy, ix]


def sweep_cells(shape: np.ndarray) -> int:
    """How many cell slots a sweep over `shape` has (edge tiles counted whole)."""
    tiles = -(-int(shape[0]) // TILE) * -(-int(shape[1]) // TILE)
    return tiles * TILE * TILE * int(shape[2])


def sweep_tiles(shape: np.ndarray) -> int:
    return -(-int(shape[0]) // TILE) * -(-int(shape[1]) // TILE)


@numba.njit(**_JIT)
def sweep_screen(grid: np.ndarray, slopes: np.ndarray, block: float, spacing: float,
                 extent: tuple[float, float], profile: bool, first: int, count: int,
                 stride: int, shape: np.ndarray, origin: np.ndarray, pitch: np.ndarray,
                 headings: np.ndarray, history: np.ndarray, sigma: float, spread: np.ndarray,
                 margin: float, cap: float, limit: float, keep: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The `keep` best of cells `first` .. `first + count` of a sweep over a grid of start
    poses, best first.

    The grid (`shape`: x, y and heading counts) is cut into tiles of `TILE` x `TILE`
    positions; the sweep visits tile (i * stride) mod tiles i-th, so any stretch of it is
    spread over the whole map, and within a tile each heading in turn over its positions,
    so neighbouring cells read neighbouring samples (on an 80-unit map a cell order with
    no locality missed the cache on most lookups: 1 us a cell instead of 0.15). A cell's
    position is `origin` + (index + 0.5) * `pitch`, its heading one of `headings`
    (`shape[2]` of them). A cell's misfit is the sum over readings of
    min(z^2, cap), z its relative height residual over the sd a pose in the cell could
    explain: `sigma` widened by how far such a pose can move the reading (`spread` (K,),
    metres; entry 0 for the first contact) times the steepest slope near where it lands
    (`slopes`, a coarse grid of blocks `block` metres a side). A reading off the map, or
    a blocked step's target on it, costs `cap`. Only cells within `limit` count, and once
    `keep` are held a cell must beat the worst of them: the sum is abandoned as soon as it
    cannot, so most cells cost a reading or two.
    """
    side = TILE
    area = side * side
    tiles_x = (shape[0] + side - 1) // side
    tiles = tiles_x * ((shape[1] + side - 1) // side)
    per_tile = area * shape[2]
    k = history.shape[0]
    # each heading's rotation of each reading, once: a cell then costs additions
    heading = np.empty(shape[2])
    cos_h, sin_h = np.empty(shape[2]), np.empty(shape[2])
    turned = np.empty((shape[2], k, 2))
    for ih in range(shape[2]):
        heading[ih] = headings[ih]
        co, si = math.cos(heading[ih]), math.sin(heading[ih])
        cos_h[ih], sin_h[ih] = co, si
        for j in range(k):
            turned[ih, j, 0] = co * history[j, 0] - si * history[j, 1]
            turned[ih, j, 1] = si * history[j, 0] + co * history[j, 1]
    walled = np.zeros(k, dtype=np.bool_)
    for j in range(k):
        walled[j] = history.shape[1] >= 5 and (history[j, 3] != 0.0 or history[j, 4] != 0.0)
    # a tile's positions, shared by its headings: centre, first-contact height, its variance
    at_x, at_y = np.empty(area), np.empty(area)
    at_z, at_var = np.empty(area), np.empty(area)
    on = np.zeros(area, dtype=np.bool_)
    poses = np.empty((keep, 3))
    misfit = np.empty(keep)
    held, worst = 0, 0
    bound = limit
    c, end = first, first + count
    while c < end:  # one tile's stretch per pass: no division per cell
        order_in_sweep = c // per_tile
        tile = (order_in_sweep * stride) % tiles
        for q in range(area):
            ix = (tile % tiles_x) * side + q % side
            iy = (tile // tiles_x) * side + q // side
            on[q] = ix < shape[0] and iy < shape[1]  # not past the map's edge
            if on[q]:
                at_x[q] = origin[0] + (ix + 0.5) * pitch[0]
                at_y[q] = origin[1] + (iy + 0.5) * pitch[1]
                at_z[q] = _height(grid, spacing, at_x[q], at_y[q])
                at_var[q] = sigma * sigma + (
                    _block(slopes, block, at_x[q], at_y[q]) * spread[0]) ** 2
        within = c - order_in_sweep * per_tile
        ih, q = within // area, within % area
        stop = min(end, (order_in_sweep + 1) * per_tile)
        while c < stop:
            if on[q]:
                px, py, z0, var0 = at_x[q], at_y[q], at_z[q], at_var[q]
                total = 0.0
                for j in range(1, k):
                    x, y = px + turned[ih, j, 0], py + turned[ih, j, 1]
                    if not _inside(x, y, extent, profile, margin) or (
                            walled[j] and not _edge_explains(px, py, cos_h[ih], sin_h[ih],
                                                             history[j], extent, profile,
                                                             margin)):
                        total += cap
                    else:
                        r = _height(grid, spacing, x, y) - z0 - history[j, 2]
                        g = _block(slopes, block, x, y) * spread[j]
                        total += min(r * r / (var0 + g * g), cap)
                    if total > bound:
                        break
                if total <= bound:
                    slot = held if held < keep else worst
                    poses[slot, 0], poses[slot, 1], poses[slot, 2] = px, py, heading[ih]
                    misfit[slot] = total
                    if held < keep:
                        held += 1
                    if held == keep:  # the bar is now the worst held
                        worst = 0
                        for i in range(1, keep):
                            if misfit[i] > misfit[worst]:
                                worst = i
                        bound = min(limit, misfit[worst])
            c += 1
            q += 1
            if q == area:
                q, ih = 0, ih + 1
    order = np.argsort(misfit[:held])
    return poses[:held][order], misfit[:held][order]


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel now, not inside a deadline.

    Once per process; later calls return at once. Localizers that use the kernels call it
    from their constructors, the daemon at start (`scenario.prepare_localizers`).
    """
    global _warm
    if _warm:
        return
    grid, profile = np.zeros((2, 2)), np.zeros((1, 2))
    for g in (grid, profile):  # contact surfaces are read-only, a type of their own
        g.flags.writeable = False
    poses = np.zeros((1, 3))
    history = np.zeros((2, 3))
    for g, is_profile in ((grid, False), (profile, True)):
        sample(g, 1.0, np.zeros(1), np.zeros(1))
        r, ok = relative_residuals(g, 1.0, (1.0, 1.0), is_profile, poses, history, 0.0)
        offset_residuals(g, 1.0, (1.0, 1.0), is_profile, poses, history, 0.0)
        log_likelihood(r, ok, np.ones(2), 0.0, 1.0)
        gauss_newton(g, 1.0, poses, history, np.ones(2), 1, 1e-4, 0.0, 1.0, is_profile,
                     (1.0, 1.0))
        heights_and_jacobian(g, 1.0, np.zeros(3), history)
        slope_squares(g, 1.0, poses, history)
        sweep_screen(g, g, 1.0, 1.0, (1.0, 1.0), is_profile, 0, 1, 1,
                     np.ones(3, dtype=np.int64), np.zeros(3), np.ones(3), np.zeros(1),
                     history, 1.0,
                     np.ones(2), 0.0, 9.0, 10.0, 4)
    first_of_each_mode(poses, 1.0, 1.0)
    best_per_key(np.zeros(1, dtype=np.int64), np.zeros(1))
    information(np.zeros((1, 2, 1)), np.ones(2), 1.0)
    _warm = True
