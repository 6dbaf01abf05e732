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

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from service.localization.objects import kernels
from service.localization.objects.field import ContactField


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


def settle(field: ContactField, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray
           ) -> np.ndarray:
    """Fingertip centres (B, n, 2) pressed back onto the object under `poses`."""
    b, n = centres.shape[:2]
    out = np.empty_like(centres)
    for i in range(n):
        out[:, i], _ = kernels.project(*field.args, np.ascontiguousarray(poses),
                                       np.ascontiguousarray(centres[:, i]), float(radii[i]), 4)
    return out


@dataclass(frozen=True)
class TwistNoise:
    """How a carried object's motion strays from the rolling model, per substep: its size
    by a fraction, its translation's direction by an angle (B2's step noise)."""

    fraction: float = 0.0
    direction_sigma: float = 0.0

    @property
    def any(self) -> bool:
        return bool(self.fraction or self.direction_sigma)


EXACT = TwistNoise()


def carry(field: ContactField, poses: np.ndarray, centres: np.ndarray, radii: np.ndarray,
          moves: np.ndarray, rolls: np.ndarray, substeps: int = 8,
          noise: TwistNoise = EXACT, rng: np.random.Generator | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """Poses (B, 3) and settled fingertip centres (B, n, 2) after every finger moves its
    centre by `moves` (n, 2) and turns its tip by `rolls` (n,), from `poses` with tips at
    `centres` (B, n, 2) (`kernels.carry`). With `noise` (and `rng`) each pose strays on its
    own draw; `carry_steps` gives every intermediate state."""
    poses, centres, moves, rolls, radii = _writable(poses, centres, moves, rolls, radii)
    return kernels.carry(*field.args, poses, centres, radii, moves, rolls, substeps,
                         _draws(len(poses), substeps, noise, rng), noise.fraction,
                         noise.direction_sigma)


def carry_steps(field: ContactField, poses: np.ndarray, centres: np.ndarray,
                radii: np.ndarray, moves: np.ndarray, rolls: np.ndarray, substeps: int = 8,
                noise: TwistNoise = EXACT, rng: np.random.Generator | None = None
                ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """`carry` one substep at a time: the poses and centres after each (the same draws, so
    the same end), for a caller that spreads a motion's work over time."""
    poses, centres, moves, rolls, radii = _writable(poses, centres, moves, rolls, radii)
    draws = _draws(len(poses), substeps, noise, rng)
    for k in range(substeps):
        poses, centres = kernels.carry(*field.args, poses, centres, radii, moves / substeps,
                                       rolls / substeps, 1,
                                       np.ascontiguousarray(draws[:, k:k + 1]),
                                       noise.fraction, noise.direction_sigma)
        yield poses, centres


def _writable(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Writable C float arrays always: a broadcast view of one row is contiguous but
    read-only, a type of its own that would compile the kernel again inside an update."""
    return tuple(np.require(a, np.float64, ("C", "W")) for a in arrays)


def _draws(count: int, substeps: int, noise: TwistNoise, rng: np.random.Generator | None
           ) -> np.ndarray:
    return (rng.standard_normal((count, substeps, 3)) if noise.any and rng is not None
            else np.zeros((count, substeps, 3)))


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
