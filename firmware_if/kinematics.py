"""Forward kinematics to the fingertip centre, its Jacobian, and damped-least-squares IK.

Pure array functions over a batch of joint vectors q of shape (N, n) (a single (n,) vector
works too): the emulator, the backend and the tests all call the same maths.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_if.hand import Hand


def _rotations(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices (N, 3, 3) about unit `axis` by angles q (N,)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(q)[:, None, None], np.cos(q)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def _chain(hand: Hand, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World joint positions (N, n, 3), world joint axes (N, n, 3) and centres (N, 3)."""
    n_batch = q.shape[0]
    rot = np.broadcast_to(np.eye(3), (n_batch, 3, 3)).copy()
    pos = np.zeros((n_batch, 3))
    positions, axes = [], []
    for i, joint in enumerate(hand.joints):
        pos = pos + rot @ np.asarray(joint.origin)
        axis = np.asarray(joint.axis)
        positions.append(pos)
        axes.append(rot @ axis)
        rot = rot @ _rotations(axis, q[:, i])
    centre = pos + rot @ np.asarray(hand.tip)
    return np.stack(positions, 1), np.stack(axes, 1), centre


def _batch(q: np.ndarray | tuple[float, ...]) -> tuple[np.ndarray, bool]:
    q = np.asarray(q, dtype=np.float64)
    return (q[None, :], True) if q.ndim == 1 else (q, False)


def forward(hand: Hand, q: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """Fingertip centre in the hand frame (metres): (N, 3), or (3,) for one joint vector."""
    qb, single = _batch(q)
    centre = _chain(hand, qb)[2]
    return centre[0] if single else centre


def jacobian(hand: Hand, q: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """d centre / d q: (N, 3, n), or (3, n) for one joint vector."""
    qb, single = _batch(q)
    jac = _centre_and_jacobian(hand, qb)[1]
    return jac[0] if single else jac


def _centre_and_jacobian(hand: Hand, qb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) and Jacobians (N, 3, n) of a batch, from one pass down the chain."""
    positions, axes, centre = _chain(hand, qb)
    return centre, np.cross(axes, centre[:, None, :] - positions).transpose(0, 2, 1)


@dataclass(frozen=True)
class IKResult:
    q: np.ndarray
    """Joint angles (N, n) or (n,), always inside the limits."""
    error: np.ndarray
    """Distance (metres) left between the reached centre and the target."""
    reachable: np.ndarray
    """Whether the error is within tolerance."""


def inverse(hand: Hand, target: np.ndarray, q0: np.ndarray | tuple[float, ...], *,
            damping: float = 1e-3, tolerance: float = 1e-5, iterations: int = 100
            ) -> IKResult:
    """Damped least squares from `q0` towards `target` centre(s), clamped to joint limits.

    Unreachable targets (outside the workspace or the limits) come back with the nearest
    reached posture and `reachable=False`, never an exception.
    """
    qb, single = _batch(q0)
    tb = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if tb.shape[0] != qb.shape[0]:
        tb = np.broadcast_to(tb, (qb.shape[0], 3))
    lo, hi = hand.lower, hand.upper
    q = np.clip(qb.copy(), lo, hi)
    eye = np.eye(3)
    for _ in range(iterations):
        centre, jac = _centre_and_jacobian(hand, q)
        err = tb - centre
        if np.all(np.linalg.norm(err, axis=1) <= tolerance):
            break
        jjt = jac @ jac.transpose(0, 2, 1) + damping**2 * eye
        dq = (jac.transpose(0, 2, 1) @ np.linalg.solve(jjt, err[:, :, None]))[:, :, 0]
        q = np.clip(q + dq, lo, hi)
    error = np.linalg.norm(tb - forward(hand, q), axis=1)
    reachable = error <= tolerance
    if single:
        return IKResult(q[0], error[0:1].reshape(()), reachable[0:1].reshape(()))
    return IKResult(q, error, reachable)
