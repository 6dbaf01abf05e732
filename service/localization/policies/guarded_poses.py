"""The poses the grasp gate guards beside the plausible hypotheses, and how they group into
modes (`grasp_gated.py`).

The hypotheses are samples of a continuous uncertainty over the object's pose, and the
grasp's quality can change fast across it. So the gate also holds, weightless, for each
mode's neighbours a spread away (`with_spread`) and for poses the readings allow in the gaps
between samples (`with_cover`); and a mode's poses are judged together (`mode_labels`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from service.localization.localizers.convergence import distinct, within

if TYPE_CHECKING:
    from service.localization.policies.grasp_gated import HandView

SPREAD_CAP = (0.0015, np.deg2rad(3.0))
"""Largest position (metres) and heading (radians) sd the gate's neighbours stand for: a
wider spread is the pool's to cover."""
FLOOR_SDS = 2.5
"""Sds of the world's outline mismatch the gate's neighbours stand for at least
(`spread_floor`)."""
MODE_SHARE = 0.005
"""Least share of the plausible weight a mode's heaviest pose needs for the gate to guard
the mode's spread."""
MODE_CELL = (0.0025, np.deg2rad(5.0))
"""Position (metres) and heading (radians) apart that two poses are distinct modes."""
MODES = 16
"""Most modes whose spread the gate guards."""
COVER = 32
"""Most plausible poses (the heaviest first) whose gaps the gate's cover fills."""
COVER_LENGTH = 0.02
"""Metres that one radian of heading counts as when measuring gaps between poses (about
an object's radius: a turn moves its contour by that much per radian)."""
COVER_GAP = (0.0005, 0.004)
"""Least and largest step (scaled metres) from a pose to the cover poses beside it."""


def with_spread(poses: np.ndarray, weights: np.ndarray, spread: tuple[float, float],
                floor: tuple[float, float] = (0.0, 0.0)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each plausible mode's neighbours two sds away (at most `SPREAD_CAP`) in heading and
    in each position axis, weightless but guarded by the gate like a likely pose: near a
    rounded corner a pose a couple of degrees off puts the contact where the grasp is far
    weaker (rounded:9, seed 9, three fingers: the estimate 2.7 degrees off, the grasp
    predicted sound, the object dropped). Every mode, not only the leader's: the truth
    may lie in a mode of a few percent (rounded:39, seed 39, two fingers: its mode held
    1.7-4.5 %, its own spread took the grasp from 1.7 to 0.15 N). The sd is the leader's.
    Returns poses, weights and the mask of the neighbours."""
    position, heading = spread
    guard = np.zeros(len(poses), dtype=bool)
    if not (np.isfinite(position) and np.isfinite(heading)) or (position == 0 and heading == 0):
        return poses, weights, guard
    position = 2 * min(max(position, floor[0]), SPREAD_CAP[0])
    heading = 2 * min(max(heading, floor[1]), SPREAD_CAP[1])
    offsets = np.array([[0, 0, heading], [0, 0, -heading], [position, 0, 0],
                        [-position, 0, 0], [0, position, 0], [0, -position, 0]])
    heads = modes(poses, weights)
    around = (poses[heads][:, None, :] + offsets[None]).reshape(-1, 3)
    return (np.vstack([poses[:1], around, poses[1:]]),
            np.concatenate([weights[:1], np.zeros(len(around)), weights[1:]]),
            np.concatenate([[False], np.ones(len(around), dtype=bool), guard[1:]]))


def spread_floor(mismatch_sd: float, max_radius: float) -> tuple[float, float]:
    """The least spread (metres, radians) the gate's neighbours stand for: `FLOOR_SDS` of
    the world's outline mismatch, in position and, over the object's lever, in heading.
    The pool's own spread says how well poses fit the model's outline, not how far the
    world's puts the truth: three fingers on a held-out five-lobed outline claimed 0.14
    degrees while the leader lay 2.1 degrees and 1 mm from the truth (seed 3), and a turn
    predicted at 1.10 N under every plausible pose dropped the object. Without mismatch
    (a noise-free world) there is no floor."""
    return FLOOR_SDS * mismatch_sd, FLOOR_SDS * mismatch_sd / max(max_radius, 1e-9)


def mode_labels(poses: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per pose, the index of the first mode head (`modes`) within `MODE_CELL` of it, or
    -1: which poses sample the same mode."""
    heads = modes(poses, weights) if weights.sum() > 0 else np.empty(0, dtype=int)
    labels = np.full(len(poses), -1)
    for k, h in enumerate(heads[::-1]):  # the heaviest head last: it wins a shared pose
        labels[within(poses, poses[h], *MODE_CELL)] = len(heads) - 1 - k
    return labels


def modes(poses: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Indices of the heaviest pose of each distinct mode (`MODE_CELL` apart) holding at
    least `MODE_SHARE` of the weight, at most `MODES`, the leader first."""
    heavy = np.flatnonzero(weights >= MODE_SHARE * weights.sum())
    return heavy[distinct(poses[heavy], weights[heavy], *MODE_CELL)][:MODES]


def with_cover(view: HandView, poses: np.ndarray) -> np.ndarray:
    """The poses the readings still allow between the plausible ones, weightless but
    guarded: the hypotheses are samples of a continuum, and an opposed grasp's quality is
    so sensitive to the pose that the truth between two samples can drop the object where
    both hold it (rounded:7, seed 7, two fingers: the nearest hypothesis 1.5 mm and 1.4
    degrees from the truth, predicted 1.0 N, the truth gave 0.10 N). Beside each of the
    `COVER` heaviest poses, half-way and all the way to the pool's typical gap, along the
    direction the fingertips' readings constrain least (where the continuum runs); a cover
    pose under which the grasp does not hold the object is dropped by the policy as any
    other. Returns the cover poses (k, 3)."""
    anchors = poses[:COVER]
    if len(poses) < 2 or len(view.fingers) == 0:
        return np.empty((0, 3))
    scale = np.array([1.0, 1.0, COVER_LENGTH])
    gap = float(np.clip(_typical_gap(poses * scale), *COVER_GAP))
    loose, next_loose, tight = _loosest(view, anchors)  # (a, 3) scaled directions, (a,)
    across = np.minimum(gap, 2 * max(view.sigma, 1e-4) / np.maximum(tight, 1e-9))[:, None]
    steps = np.concatenate([f * gap * loose for f in (0.5, -0.5, 1.0, -1.0)]
                           + [f * across * next_loose for f in (1.0, -1.0)]) / scale
    return np.tile(anchors, (6, 1)) + steps


def _typical_gap(points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point."""
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _loosest(view: HandView, poses: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pose, the unit pose changes (a, 3) (scaled as in `with_cover`) that move the
    object's contour least and next-least across the fingertip centres - the readings' own
    null direction, and the one they constrain least besides - and how many metres the
    latter moves it per scaled metre (a,)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    w = view.centres[None] - poses[:, None, :2]  # (a, n, 2)
    u = c[:, None] * w[..., 0] + s[:, None] * w[..., 1]
    v = -s[:, None] * w[..., 0] + c[:, None] * w[..., 1]
    _, gu, gv = view.field.distance(u, v)
    nx, nz = c[:, None] * gu - s[:, None] * gv, s[:, None] * gu + c[:, None] * gv
    turn = (gu * v - gv * u) / COVER_LENGTH  # d(distance)/d(heading), scaled
    jac = np.stack([-nx, -nz, turn], axis=-1)  # (a, n, 3)
    _, sv, vt = np.linalg.svd(jac, full_matrices=True)
    second = sv[:, 1] if sv.shape[1] > 1 else np.zeros(len(poses))  # one finger: loose too
    return vt[:, -1], vt[:, -2], second


def in_mode(poses: np.ndarray, i: int) -> np.ndarray:
    """Which poses lie in pose i's mode (`MODE_CELL`)."""
    return within(poses, poses[i], *MODE_CELL)


def ambiguous(poses: np.ndarray, weights: np.ndarray) -> bool:
    """Whether a plausible pose of any weight lies outside the leader's mode (`MODE_CELL`):
    then more readings where they agree cannot settle it."""
    far = ~within(poses, poses[0], *MODE_CELL)
    return bool(np.any(far & (weights >= 1e-3 * weights[0])))

