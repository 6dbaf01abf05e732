"""Array maths shared by the probabilistic localizers: how well start poses fit a history.

Every function works on many hypotheses at once (STYLE.md item 2). A *history* is the
(K + 1, 3) array of finger-frame displacements (dx, dy, dz) since first contact, row 0
being the first contact itself (zeros). For a start pose (x0, y0, heading), reading k
predicts the centre height C(p0 + R(heading) (dx_k, dy_k)) - C(p0) relative to the first
contact; the residual is that minus dz_k. Lookups are bilinear, like `ContactSurface.lookup`,
but also give the gradient, which the Gauss-Newton polish and the least-squares fit need.
"""

from __future__ import annotations

import weakref

import numpy as np

from service.localizers.base import wrap_angle
from service.surface import ContactSurface

_SLOPES: weakref.WeakKeyDictionary[ContactSurface, float] = weakref.WeakKeyDictionary()


def sample(surface: ContactSurface, x: np.ndarray, y: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre height and its gradient (d/dx, d/dy) at (x, y), bilinear, clamped at the edge."""
    grid = surface.centre_heights
    h = surface.map.spacing
    rows, cols = grid.shape
    fx = np.clip(np.asarray(x, dtype=np.float64) / h, 0.0, cols - 1.0)
    ix = np.minimum(fx.astype(np.intp), cols - 2)
    tx = fx - ix
    flat = grid.ravel()
    if rows == 1:
        v0, v1 = flat[ix], flat[ix + 1]
        return v0 + tx * (v1 - v0), (v1 - v0) / h, np.zeros_like(tx)
    fy = np.clip(np.asarray(y, dtype=np.float64) / h, 0.0, rows - 1.0)
    iy = np.minimum(fy.astype(np.intp), rows - 2)
    ty = fy - iy
    base = iy * cols + ix
    v00, v01 = flat[base], flat[base + 1]
    v10, v11 = flat[base + cols], flat[base + cols + 1]
    top = v00 + tx * (v01 - v00)
    bottom = v10 + tx * (v11 - v10)
    value = top + ty * (bottom - top)
    gx = ((1 - ty) * (v01 - v00) + ty * (v11 - v10)) / h
    gy = (bottom - top) / h
    return value, gx, gy


def typical_slope(surface: ContactSurface) -> float:
    """RMS gradient of the contact surface: converts a pose range into a height range."""
    cached = _SLOPES.get(surface)
    if cached is None:
        gy, gx = np.gradient(surface.centre_heights, surface.map.spacing)
        cached = float(np.sqrt(np.mean(gx**2 + gy**2))) if surface.centre_heights.size else 1.0
        _SLOPES[surface] = cached = max(cached, 1e-3)
    return cached


def positions(poses: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map (x, y) of the centre for each pose (N, 3) at each reading (K): arrays (N, K)."""
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    dx, dy = history[np.newaxis, :, 0], history[np.newaxis, :, 1]
    return poses[:, 0:1] + c * dx - s * dy, poses[:, 1:2] + s * dx + c * dy


def residuals(surface: ContactSurface, poses: np.ndarray, history: np.ndarray, z0: np.ndarray,
              margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Height residuals (N, K) of readings `history` (K, 3) and whether each lies on the map.

    `z0` (N,) is each pose's centre height at first contact.
    """
    x, y = positions(poses, history)
    z, _, _ = sample(surface, x, y)
    return z - z0[:, np.newaxis] - history[np.newaxis, :, 2], surface.map.inside(x, y, margin)


def sigmas(sensor_sigma: float, slope: float, history: np.ndarray, pos_range: float,
           head_range: float) -> np.ndarray:
    """Residual sd per reading (K,) for hypotheses that each stand for a range of poses.

    A pose off by `pos_range` metres and `head_range` radians puts reading k off by up to
    pos_range + |d_k| head_range, which a slope turns into height (paper Eq. 4).
    """
    lever = np.hypot(history[:, 0], history[:, 1])
    spread = slope * (pos_range + lever * head_range)
    return np.sqrt(sensor_sigma**2 + spread**2)


def log_likelihood(residual: np.ndarray, on_map: np.ndarray, sigma: np.ndarray,
                   outlier_probability: float, outlier_range: float) -> np.ndarray:
    """Sum over readings of a Gaussian-plus-uniform log likelihood; off-map readings fail."""
    z = residual / sigma
    inlier = (1 - outlier_probability) * np.exp(-0.5 * z * z) / sigma
    ll = np.log(inlier + outlier_probability / outlier_range + 1e-300)
    ll = np.where(on_map, ll, -1e3)
    return ll.sum(axis=-1)


def gauss_newton(surface: ContactSurface, poses: np.ndarray, history: np.ndarray,
                 weights: np.ndarray, iterations: int = 3, damping: float = 1e-4,
                 max_move: float | None = None) -> np.ndarray:
    """A few damped Gauss-Newton steps for every pose at once, with a free height offset.

    Minimizes sum_k w_k (C(p_k) - c - dz_k)^2 over (x0, y0, heading, c) with c eliminated,
    so the first reading is just another noisy reading. Steps are capped at `max_move`
    metres (and max_move / lever radians) so a pose never jumps to another basin. The
    3 x 3 normal equations are solved in closed form, vectorized over poses.
    """
    poses = poses.copy()
    w = weights / weights.sum()
    dx, dy = history[np.newaxis, :, 0], history[np.newaxis, :, 1]
    lever = max(float(np.max(np.hypot(history[:, 0], history[:, 1]))), max_move or 0.0)
    for _ in range(iterations):
        x, y = positions(poses, history)
        z, gx, gy = sample(surface, x, y)
        c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
        gh = gx * (-s * dx - c * dy) + gy * (c * dx - s * dy)
        cols = [v - (v @ w)[:, np.newaxis] for v in (gx, gy, gh)]  # the offset, eliminated
        e = z - history[np.newaxis, :, 2]
        e = e - (e @ w)[:, np.newaxis]
        a = [[(cols[i] * cols[j]) @ w for j in range(3)] for i in range(3)]
        b = [(cols[i] * e) @ w for i in range(3)]
        bump = damping * (1.0 + a[0][0] + a[1][1] + a[2][2]) / 3
        for i in range(3):
            a[i][i] = a[i][i] + bump
        step = -_solve3(a, b)
        if max_move is not None:
            scale = np.maximum(np.hypot(step[:, 0], step[:, 1]) / max_move,
                               np.abs(step[:, 2]) * lever / max_move)
            step /= np.maximum(scale, 1.0)[:, np.newaxis]
        poses += step
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def _solve3(a: list[list[np.ndarray]], b: list[np.ndarray]) -> np.ndarray:
    """Solve symmetric 3 x 3 systems given entry-wise as arrays (Cramer's rule)."""
    c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1]
    c01 = a[1][2] * a[2][0] - a[1][0] * a[2][2]
    c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0]
    det = a[0][0] * c00 + a[0][1] * c01 + a[0][2] * c02
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    c11 = a[0][0] * a[2][2] - a[0][2] * a[2][0]
    c12 = a[0][1] * a[2][0] - a[0][0] * a[2][1]
    c22 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
    x0 = (c00 * b[0] + c01 * b[1] + c02 * b[2]) / det
    x1 = (c01 * b[0] + c11 * b[1] + c12 * b[2]) / det
    x2 = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
    return np.column_stack([x0, x1, x2])


def offset_residuals(surface: ContactSurface, poses: np.ndarray, history: np.ndarray,
                     margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, K) of every reading, first contact included, with the height offset
    between hand and map fitted per pose (so no single reading is the exact reference)."""
    x, y = positions(poses, history)
    z, _, _ = sample(surface, x, y)
    e = z - history[np.newaxis, :, 2]
    return e - e.mean(axis=1, keepdims=True), surface.map.inside(x, y, margin)
