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

from service.localization import kernels as shared
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
def _settle(grid: np.ndarray, spacing: float, ox: float, oy: float, pose: np.ndarray,
            cx: float, cz: float, radius: float, iterations: int
            ) -> tuple[float, float, float, float]:
    """A compliant fingertip aimed at (cx, cz) (hand frame) moved along the distance
    gradient until it touches the object under `pose`: its centre and the object's outward
    unit normal there, hand frame. No iterations: the normal at the centre as it is."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    wx, wz = cx - pose[0], cz - pose[1]
    u, v = c * wx + s * wz, -s * wx + c * wz
    for _ in range(iterations):
        d, gu, gv = _lookup(grid, spacing, ox, oy, u, v)
        norm = math.hypot(gu, gv)
        if norm < 1e-12:
            break
        u -= (d - radius) * gu / norm
        v -= (d - radius) * gv / norm
    _, gu, gv = _lookup(grid, spacing, ox, oy, u, v)
    norm = max(math.hypot(gu, gv), 1e-12)
    gu, gv = gu / norm, gv / norm
    return (pose[0] + c * u - s * v, pose[1] + s * u + c * v, c * gu - s * gv,
            s * gu + c * gv)


@numba.njit(**_JIT)
def project(grid: np.ndarray, spacing: float, ox: float, oy: float, poses: np.ndarray,
            centres: np.ndarray, radius: float, iterations: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """`_settle` for fingertip i aimed at `centres[i]` on the object under `poses[i]`:
    centres (N, 2) and outward unit normals (N, 2), hand frame."""
    n = poses.shape[0]
    out = np.empty((n, 2))
    normals = np.empty((n, 2))
    for i in range(n):
        out[i, 0], out[i, 1], normals[i, 0], normals[i, 1] = _settle(
            grid, spacing, ox, oy, poses[i], centres[i, 0], centres[i, 1], radius, iterations)
    return out, normals


@numba.njit(**_JIT)
def twist(points: np.ndarray, normals: np.ndarray, origin: np.ndarray, radii: np.ndarray,
          moves: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """Least-squares object twist (v_x, v_z, w) that makes the object's point at each
    contact (n, 2) move as the fingertip's surface there does: the centre's move minus
    r * roll along the tangent (no slip). See `rolling.py`."""
    normal = np.zeros((3, 4))
    for f in range(points.shape[0]):
        lx, lz = points[f, 0] - origin[0], points[f, 1] - origin[1]
        tx, tz = -normals[f, 1], normals[f, 0]
        for row in range(2):
            a0 = 1.0 if row == 0 else 0.0
            a1 = 1.0 - a0
            a2 = -lz if row == 0 else lx
            b = moves[f, row] - radii[f] * rolls[f] * (tx if row == 0 else tz)
            a = (a0, a1, a2)
            for i in range(3):
                normal[i, 3] += a[i] * b
                for j in range(3):
                    normal[i, j] += a[i] * a[j]
    for i in range(3):
        normal[i, i] += 1e-12
    return _solve3(normal)


@numba.njit(**_JIT)
def carry(grid: np.ndarray, spacing: float, ox: float, oy: float, poses: np.ndarray,
          centres: np.ndarray, radii: np.ndarray, moves: np.ndarray, rolls: np.ndarray,
          substeps: int, noise: np.ndarray, fraction: float, direction_sigma: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """Each pose (N, 3) with its fingertips at `centres` (N, n, 2), after the fingers move
    their centres by `moves` (n, 2) and turn their tips by `rolls` (n,), in `substeps`
    equal parts: per part the twist the rolling contacts impose (`twist`), perturbed by
    standard normals `noise` (N, substeps, 3) - its size by `fraction`, the translation's
    direction by `direction_sigma` - then each tip pressed back onto the object."""
    n_poses, n = poses.shape[0], centres.shape[1]
    out = poses.copy()
    tips = centres.copy()
    points = np.empty((n, 2))
    normals = np.empty((n, 2))
    part_moves = moves / substeps
    part_rolls = rolls / substeps
    for i in range(n_poses):
        for k in range(substeps):
            for f in range(n):
                _, _, nx, nz = _settle(grid, spacing, ox, oy, out[i], tips[i, f, 0],
                                       tips[i, f, 1], radii[f], 0)
                normals[f, 0], normals[f, 1] = nx, nz
                points[f, 0] = tips[i, f, 0] - radii[f] * nx
                points[f, 1] = tips[i, f, 1] - radii[f] * nz
            step = twist(points, normals, out[i, :2], radii, part_moves, part_rolls)
            scale = 1.0 + fraction * noise[i, k, 0]
            turn = direction_sigma * noise[i, k, 1]
            c, s = math.cos(turn), math.sin(turn)
            out[i, 0] += scale * (c * step[0] - s * step[1])
            out[i, 1] += scale * (s * step[0] + c * step[1])
            out[i, 2] += (1.0 + fraction * noise[i, k, 2]) * step[2]
            out[i, 2] = (out[i, 2] + math.pi) % (2 * math.pi) - math.pi
            for f in range(n):
                tips[i, f, 0], tips[i, f, 1], _, _ = _settle(
                    grid, spacing, ox, oy, out[i], tips[i, f, 0] + part_moves[f, 0],
                    tips[i, f, 1] + part_moves[f, 1], radii[f], 4)
    return out, tips


_warm = False


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel now, once per process, and the
    shared ones an object localizer's update calls (likelihoods, mode suppression): else
    each loads inside the first update that needs it (17-30 ms apiece)."""
    global _warm
    if _warm:
        return
    shared.warm_up()
    grid = np.zeros((2, 2))
    grid.flags.writeable = False  # fields are read-only, a type of their own
    poses, points, radii = np.zeros((1, 3)), np.zeros((1, 2)), np.ones(1)
    distances(grid, 1.0, 0.0, 0.0, np.zeros(1), np.zeros(1))
    residuals(grid, 1.0, 0.0, 0.0, poses, points, radii)
    residuals_and_jacobian(grid, 1.0, 0.0, 0.0, np.zeros(3), points, radii)
    gauss_newton(grid, 1.0, 0.0, 0.0, poses, points, radii, np.ones(1), 1, 1e-4, 0.0, 1.0)
    project(grid, 1.0, 0.0, 0.0, poses, points, 1.0, 1)
    carry(grid, 1.0, 0.0, 0.0, poses, np.zeros((1, 1, 2)), radii, points, radii, 1,
          np.zeros((1, 1, 3)), 0.0, 0.0)
    _warm = True
