"""Compiled inner loops over object poses x fingertip readings (numba), as `kernels.py` is
for height maps.

A pose (x, z, theta) puts object point q at R(theta) q + (x, z) in the hand plane; a
fingertip centre c then sits at object point q = R(-theta) (c - t), and touches the object
when the contour's signed distance there equals the tip's radius (Eq. 7 in 2-D). Every
function reads the signed-distance grid with the shared bilinear lookup
(`kernels._bilinear`), so a hypothesis test is one lookup. Grids are indexed [row = v,
col = u] from `origin`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from service.localization.kernels import _bilinear, _solve3

_JIT = {"cache": True, "nogil": True}


@numba.njit(**_JIT)
def _lookup(grid: np.ndarray, spacing: float, ox: float, oy: float, u: float, v: float
            ) -> tuple[float, float, float]:
    return _bilinear(grid, spacing, u - ox, v - oy)


@numba.njit(**_JIT)
def distances(grid: np.ndarray, spacing: float, ox: float, oy: float, u: np.ndarray,
              v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance and its gradient at object-frame points (flat arrays)."""
    n = u.shape[0]
    d, gu, gv = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        d[i], gu[i], gv[i] = _lookup(grid, spacing, ox, oy, u[i], v[i])
    return d, gu, gv


@numba.njit(**_JIT)
def residuals(grid: np.ndarray, spacing: float, ox: float, oy: float, poses: np.ndarray,
              points: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(N, K): signed distance of each reading's centre (K, 2) from the object under each
    pose (N, 3), minus the reading's tip radius: zero for a centre in contact."""
    n, k = poses.shape[0], points.shape[0]
    out = np.empty((n, k))
    for i in range(n):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        for j in range(k):
            wx, wz = points[j, 0] - poses[i, 0], points[j, 1] - poses[i, 1]
            out[i, j] = _lookup(grid, spacing, ox, oy, c * wx + s * wz,
                                -s * wx + c * wz)[0] - radii[j]
    return out


@numba.njit(**_JIT)
def residuals_and_jacobian(grid: np.ndarray, spacing: float, ox: float, oy: float,
                           pose: np.ndarray, points: np.ndarray, radii: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """For one pose (3,): residuals (K,) and their derivatives by (x, z, theta) (K, 3)."""
    k = points.shape[0]
    r = np.empty(k)
    jac = np.empty((k, 3))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    for j in range(k):
        wx, wz = points[j, 0] - pose[0], points[j, 1] - pose[1]
        u, v = c * wx + s * wz, -s * wx + c * wz
        d, gu, gv = _lookup(grid, spacing, ox, oy, u, v)
        r[j] = d - radii[j]
        jac[j, 0] = -(c * gu - s * gv)
        jac[j, 1] = -(s * gu + c * gv)
        jac[j, 2] = gu * v - gv * u
    return r, jac


@numba.njit(**_JIT)
def gauss_newton(grid: np.ndarray, spacing: float, ox: float, oy: float, poses: np.ndarray,
                 points: np.ndarray, radii: np.ndarray, weights: np.ndarray, iterations: int,
                 damping: float, max_move: float, lever: float) -> np.ndarray:
    """Damped Gauss-Newton steps on every pose's (x, z, theta) towards the readings; a step
    is capped at `max_move` metres (and max_move / lever radians) so no pose jumps into
    another mode's basin; max_move <= 0 leaves it uncapped."""
    n, k = poses.shape[0], points.shape[0]
    out = poses.copy()
    normal = np.zeros((3, 4))
    for i in range(n):
        for _ in range(iterations):
            r, jac = residuals_and_jacobian(grid, spacing, ox, oy, out[i], points, radii)
            normal[:, :] = 0.0
            for j in range(k):
                for a in range(3):
                    normal[a, 3] += weights[j] * jac[j, a] * r[j]
                    for b in range(a, 3):
                        normal[a, b] += weights[j] * jac[j, a] * jac[j, b]
            for a in range(3):
                for b in range(a):
                    normal[a, b] = normal[b, a]
            bump = damping * (1.0 + normal[0, 0] + normal[1, 1] + normal[2, 2]) / 3
            for a in range(3):
                normal[a, a] += bump
            step = _solve3(normal)
            if max_move > 0:
                scale = max(math.hypot(step[0], step[1]) / max_move,
                            abs(step[2]) * lever / max_move, 1.0)
                step /= scale
            out[i, 0] -= step[0]
            out[i, 1] -= step[1]
            out[i, 2] -= step[2]
        out[i, 2] = (out[i, 2] + math.pi) % (2 * math.pi) - math.pi
    return out


@numba.njit(**_JIT)
def project(grid: np.ndarray, spacing: float, ox: float, oy: float, poses: np.ndarray,
            centres: np.ndarray, radius: float, iterations: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """Where a compliant fingertip aimed at `centres[i]` (hand frame) comes to rest on the
    object under `poses[i]`: moved along the distance gradient until it touches. Returns
    the centres (N, 2) and the object's outward unit normals there (N, 2), hand frame."""
    n = poses.shape[0]
    out = np.empty((n, 2))
    normals = np.empty((n, 2))
    for i in range(n):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        wx, wz = centres[i, 0] - poses[i, 0], centres[i, 1] - poses[i, 1]
        u, v = c * wx + s * wz, -s * wx + c * wz
        gu, gv = 0.0, 0.0
        for _ in range(iterations):
            d, gu, gv = _lookup(grid, spacing, ox, oy, u, v)
            norm = math.hypot(gu, gv)
            if norm < 1e-12:
                break
            gu, gv = gu / norm, gv / norm
            u -= (d - radius) * gu
            v -= (d - radius) * gv
        _, gu, gv = _lookup(grid, spacing, ox, oy, u, v)
        norm = max(math.hypot(gu, gv), 1e-12)
        gu, gv = gu / norm, gv / norm
        out[i, 0] = poses[i, 0] + c * u - s * v
        out[i, 1] = poses[i, 1] + s * u + c * v
        normals[i, 0] = c * gu - s * gv
        normals[i, 1] = s * gu + c * gv
    return out, normals


_warm = False


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel now, once per process."""
    global _warm
    if _warm:
        return
    grid = np.zeros((2, 2))
    grid.flags.writeable = False  # fields are read-only, a type of their own
    poses, points, radii = np.zeros((1, 3)), np.zeros((1, 2)), np.ones(1)
    distances(grid, 1.0, 0.0, 0.0, np.zeros(1), np.zeros(1))
    residuals(grid, 1.0, 0.0, 0.0, poses, points, radii)
    residuals_and_jacobian(grid, 1.0, 0.0, 0.0, np.zeros(3), points, radii)
    gauss_newton(grid, 1.0, 0.0, 0.0, poses, points, radii, np.ones(1), 1, 1e-4, 0.0, 1.0)
    project(grid, 1.0, 0.0, 0.0, poses, points, 1.0, 1)
    _warm = True
