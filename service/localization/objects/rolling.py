"""Rolling contact kinematics: how the fingers' motions carry the object (manipulation).

Quasi-static: the object goes where the fingers put it. A fingertip (a disc of radius r in
the hand plane, centre c) that moves by dc and turns by dpsi moves its surface point at the
contact p = c - r n by dc - r dpsi t (n the object's outward normal, t = n turned a quarter
counter-clockwise). Without slip the object's point there moves the same, so the object's
twist (v, w) - its centroid's motion and its turn - satisfies, per contact,

    v + w perp(p - o) = dc - r dpsi t.

With two or more fingers that is more equations than unknowns: least squares gives the
twist, and what it leaves over the fingers' compliance absorbs. A finite move is taken in
substeps, each re-reading the contacts; afterwards each fingertip settles back onto the
moved object (it presses). The simulated hand and the localizers' motion model call the
same `carry`, so what the localizer predicts for the true pose is what the world does, up to
the world's noise.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.localization.objects import kernels
from service.localization.objects.field import ContactField

Noise = Callable[[np.ndarray], np.ndarray]
"""Perturbs a batch of substep twists (B, 3) -> (B, 3): the world's (or the model's) noise."""


def contacts(field: ContactField, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Contact points (B, n, 2) and outward normals (B, n, 2) of fingertips at `centres`
    (B, n, 2) on the object under `poses` (B, 3): where each tip would rest."""
    b, n = centres.shape[:2]
    rep = np.repeat(poses, n, axis=0)
    flat = np.ascontiguousarray(centres.reshape(-1, 2))
    normals = np.empty_like(flat)
    for i in range(n):  # one radius per finger
        idx = np.arange(i, b * n, n)
        _, normals[idx] = kernels.project(*field.args, np.ascontiguousarray(rep[idx]),
                                          np.ascontiguousarray(flat[idx]), float(radii[i]), 0)
    normals = normals.reshape(b, n, 2)
    return centres - radii[None, :, None] * normals, normals


def twist(points: np.ndarray, normals: np.ndarray, origins: np.ndarray, radii: np.ndarray,
          moves: np.ndarray, rolls: np.ndarray) -> np.ndarray:
    """Least-squares object twist (B, 3) = (v_x, v_z, w) from the fingers' centre moves
    (n, 2) and tip turns (n,) at contacts `points`/`normals` (B, n, 2)."""
    lever = points - origins[:, None, :]
    t = np.stack([-normals[..., 1], normals[..., 0]], axis=-1)
    rhs = moves[None] - (radii * rolls)[None, :, None] * t  # (B, n, 2)
    b, n = points.shape[:2]
    a = np.zeros((b, n, 2, 3))
    a[..., 0, 0] = 1.0
    a[..., 1, 1] = 1.0
    a[..., 0, 2] = -lever[..., 1]
    a[..., 1, 2] = lever[..., 0]
    a = a.reshape(b, 2 * n, 3)
    normal = np.einsum("bki,bkj->bij", a, a) + 1e-12 * np.eye(3)
    return np.linalg.solve(normal, np.einsum("bki,bk->bi", a, rhs.reshape(b, 2 * n))[..., None]
                           )[..., 0]


def apply_twist(poses: np.ndarray, twists: np.ndarray) -> np.ndarray:
    """Poses (B, 3) after turning by w about their centroid and shifting it by v."""
    out = poses + twists
    out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return out


def settle(field: ContactField, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray
           ) -> np.ndarray:
    """Fingertip centres (B, n, 2) pressed back onto the object under `poses`."""
    b, n = centres.shape[:2]
    out = np.empty_like(centres)
    for i in range(n):
        out[:, i], _ = kernels.project(*field.args, np.ascontiguousarray(poses),
                                       np.ascontiguousarray(centres[:, i]), float(radii[i]), 4)
    return out


def carry(field: ContactField, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
          moves: np.ndarray, rolls: np.ndarray, substeps: int = 8,
          noise: Noise | None = None,
          on_substep: Callable[[np.ndarray, np.ndarray], None] | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """Poses (B, 3) and settled fingertip centres (B, n, 2) after every finger moves its
    centre by `moves` (n, 2) and turns its tip by `rolls` (n,), from `poses` with tips at
    `centres` (B, n, 2). `on_substep(poses, centres)` sees every intermediate state."""
    poses = np.array(poses, dtype=np.float64)
    centres = np.array(centres, dtype=np.float64)
    moves = np.asarray(moves, dtype=np.float64) / substeps
    rolls = np.asarray(rolls, dtype=np.float64) / substeps
    for _ in range(substeps):
        points, normals = contacts(field, poses, centres, radii)
        step = twist(points, normals, poses[:, :2], radii, moves, rolls)
        if noise is not None:
            step = noise(step)
        poses = apply_twist(poses, step)
        centres = settle(field, poses, centres + moves[None], radii)
        if on_substep is not None:
            on_substep(poses, centres)
    return poses, centres


def plan_turn(field: ContactField, pose: np.ndarray, centres: np.ndarray, radii: np.ndarray,
              turn: float, substeps: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Centre moves (n, 2) and tip turns (n,) that turn the object by `turn` radians about
    its centroid in place, under `pose`: each tip spins to roll the object and follows the
    outline in and out along its normal."""
    pose = np.array(pose, dtype=np.float64)
    centres = np.array(centres, dtype=np.float64)
    moves = np.zeros_like(centres)
    rolls = np.zeros(len(centres))
    w = turn / substeps
    for _ in range(substeps):
        points, normals = contacts(field, pose[None], centres[None], radii)
        points, normals = points[0], normals[0]
        lever = points - pose[:2]
        velocity = w * np.column_stack([-lever[:, 1], lever[:, 0]])  # the object's point
        t = np.column_stack([-normals[:, 1], normals[:, 0]])
        along_n = np.einsum("ij,ij->i", velocity, normals)
        rolls += -np.einsum("ij,ij->i", velocity, t) / radii
        moved_pose = pose.copy()
        moved_pose[2] += w
        target = settle(field, moved_pose[None], (centres + along_n[:, None] * normals)[None],
                        radii)[0]
        moves += target - centres
        centres, pose = target, moved_pose
    return moves, rolls
