"""`firmware_if.kinematics` compiled for the grasp planner's batches (numba).

The grasp-gated policy solves a finger's inverse kinematics and Jacobians hundreds of
times a decision, on a few joint vectors each time; numpy's per-call overhead made that
most of a decision. These are the same maths (Rodrigues down the chain, damped least
squares with the batch stopping together, clamped to the joint limits) as compiled loops.
`firmware_if.kinematics` stays numpy: the servo and emulator paths must never wait for a
JIT compile. `tests/service/test_chain_kernels.py` holds the two to the same answers.
"""

from __future__ import annotations

from functools import lru_cache

import numba
import numpy as np

from firmware_if.kinematics import STALLED, Chain, base_frame
from service.localization.kernels import _solve3

_JIT = {"cache": True, "nogil": True}


@lru_cache(maxsize=64)
def _constants(chain: Chain) -> tuple[np.ndarray, ...]:
    """What the compiled chain takes: base rotation (3, 3) and origin (3,), joint origins
    and axes (n, 3), their cross-product matrices K and K @ K (n, 3, 3), the tip offset
    (3,), and the joint limits (n,)."""
    base_rot, base_pos = base_frame(chain)
    axes = np.array([j.axis for j in chain.joints], dtype=np.float64)
    skews = np.array([[[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]] for x, y, z in axes])
    return (base_rot, base_pos, np.array([j.origin for j in chain.joints], dtype=np.float64),
            axes, skews, skews @ skews, np.asarray(chain.tip, dtype=np.float64),
            np.asarray(chain.lower, dtype=np.float64), np.asarray(chain.upper, dtype=np.float64))


@numba.njit(**_JIT)
def _chain_row(base_rot: np.ndarray, base_pos: np.ndarray, origins: np.ndarray,
               axes: np.ndarray, skews: np.ndarray, squares: np.ndarray, tip: np.ndarray,
               q: np.ndarray, centre: np.ndarray, jac: np.ndarray) -> None:
    """One joint vector's centre (3,) and Jacobian (3, n) into `centre` and `jac`: down the
    chain, each joint's frame turned by Rodrigues' R = I + sin q K + (1 - cos q) K^2."""
    n = origins.shape[0]
    rot = base_rot.copy()
    turned = np.empty((3, 3))
    pos = base_pos.copy()
    positions = np.empty((n, 3))
    world = np.empty((n, 3))
    for i in range(n):
        for a in range(3):
            pos[a] += rot[a, 0] * origins[i, 0] + rot[a, 1] * origins[i, 1] + (
                rot[a, 2] * origins[i, 2])
        for a in range(3):
            positions[i, a] = pos[a]
            world[i, a] = rot[a, 0] * axes[i, 0] + rot[a, 1] * axes[i, 1] + (
                rot[a, 2] * axes[i, 2])
        s, c = np.sin(q[i]), np.cos(q[i])
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for m in range(3):
                    r = ((1.0 if m == b else 0.0) + s * skews[i, m, b]
                         + (1 - c) * squares[i, m, b])
                    acc += rot[a, m] * r
                turned[a, b] = acc
        rot[:, :] = turned
    for a in range(3):
        centre[a] = pos[a] + rot[a, 0] * tip[0] + rot[a, 1] * tip[1] + rot[a, 2] * tip[2]
    for i in range(n):
        lx = centre[0] - positions[i, 0]
        ly = centre[1] - positions[i, 1]
        lz = centre[2] - positions[i, 2]
        jac[0, i] = world[i, 1] * lz - world[i, 2] * ly
        jac[1, i] = world[i, 2] * lx - world[i, 0] * lz
        jac[2, i] = world[i, 0] * ly - world[i, 1] * lx


@numba.njit(**_JIT)
def _chain_batch(base_rot: np.ndarray, base_pos: np.ndarray, origins: np.ndarray,
                 axes: np.ndarray, skews: np.ndarray, squares: np.ndarray, tip: np.ndarray,
                 q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) and Jacobians (N, 3, n) of joint vectors q (N, n)."""
    centres = np.empty((q.shape[0], 3))
    jac = np.empty((q.shape[0], 3, q.shape[1]))
    for row in range(q.shape[0]):
        _chain_row(base_rot, base_pos, origins, axes, skews, squares, tip, q[row],
                   centres[row], jac[row])
    return centres, jac


@numba.njit(**_JIT)
def _solve_ik(base_rot: np.ndarray, base_pos: np.ndarray, origins: np.ndarray,
              axes: np.ndarray, skews: np.ndarray, squares: np.ndarray, tip: np.ndarray,
              lower: np.ndarray, upper: np.ndarray, q0: np.ndarray, targets: np.ndarray,
              damping: float, tolerance: float, iterations: int, stalled: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Damped least squares for every row until each is within `tolerance` or an iteration
    brought it no nearer than `stalled` (the batch stops together), or `iterations` pass,
    every step clamped to the limits; the joint angles and the distance left per row."""
    batch, n = q0.shape
    q = np.minimum(np.maximum(q0, lower), upper)
    system = np.empty((3, 4))
    left = np.full(batch, np.inf)
    for _ in range(iterations):
        centres, jac = _chain_batch(base_rot, base_pos, origins, axes, skews, squares, tip, q)
        done = True
        for row in range(batch):
            e = targets[row] - centres[row]
            now = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
            if now > tolerance and left[row] - now >= stalled:
                done = False
            left[row] = now
        if done:
            break
        for row in range(batch):
            j = jac[row]
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for m in range(n):
                        acc += j[a, m] * j[b, m]
                    system[a, b] = acc + (damping * damping if a == b else 0.0)
                system[a, 3] = targets[row, a] - centres[row, a]
            x = _solve3(system)
            for m in range(n):
                step = j[0, m] * x[0] + j[1, m] * x[1] + j[2, m] * x[2]
                q[row, m] = min(max(q[row, m] + step, lower[m]), upper[m])
    centres, _ = _chain_batch(base_rot, base_pos, origins, axes, skews, squares, tip, q)
    error = np.empty(batch)
    for row in range(batch):
        e = targets[row] - centres[row]
        error[row] = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    return q, error


def _plain(a: np.ndarray) -> np.ndarray:
    """`a` as a C-contiguous, writable float64 array (copied only if it is not)."""
    return np.require(a, dtype=np.float64, requirements=["C", "W"])


def jacobians(chain: Chain, q: np.ndarray) -> np.ndarray:
    """d centre / d q (N, 3, n) of joint vectors q (N, n): `kinematics.jacobian`."""
    return _chain_batch(*_constants(chain)[:7], _plain(q))[1]


def inverse(chain: Chain, targets: np.ndarray, q0: np.ndarray, *, damping: float = 1e-3,
            tolerance: float = 1e-5, iterations: int = 100
            ) -> tuple[np.ndarray, np.ndarray]:
    """`kinematics.inverse` of targets (N, 3) from q0 (N, n): joint angles (N, n) and
    whether each target is reached within `tolerance` (N,)."""
    # contiguous and writable, whatever came: a read-only q0 (a broadcast row) is a type
    # of its own to numba, and the first turn compiled the solver again for it inside one
    # decision (1.5 s on an empty cache; three fingers on blob, seed 0, step 6)
    q, error = _solve_ik(*_constants(chain), _plain(q0), _plain(targets), float(damping),
                         float(tolerance), int(iterations), STALLED)
    return q, error <= tolerance
