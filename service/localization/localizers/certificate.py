"""The certificate: a declaration checked against every pose on the map, by branch and bound.

The sweep and the turned checks rank coarse cells by a screen and polish the best; a pose
they rank poorly is never tried. On a plate the walk stayed on plains and the sweep judged
cells on the nine readings round one anchor: the truth's cells ranked 6,154th of 27,744,
never joined the pool, and a pose 123 mm and 79 degrees off was declared while the truth
fitted the readings 42 nats better (machined_plate, seed 77, on one machine).

So before a declaration the whole pose space is searched with bounds that cannot miss:
boxes of poses (position and heading) are judged on every reading at once. Under any pose
in a box a reading lands within a disk, where the map's height lies between the least and
the greatest of the blocks the disk touches (`bound_kernels.pyramid`) and within the
steepest slope times the radius of the centre's height; the least misfit
those ranges allow, with the height offset free, bounds every pose in the box from below.
A box that cannot come within `SLACK` nats of the declared pose is ruled out; the rest are
halved down to fine boxes, whose centres are polished onto the readings and weighed as the
turned checks weigh their rivals (`turned.rivals_clear`).

Poses are held by where they put the readings' centroid (their anchor), not the first
contact: a heading's range then moves every reading least.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from service.localization import bound_kernels
from service.localization.localizers.convergence import distinct, within
from service.localization.localizers.fitting import gauss_newton, on_pose_space, unanchored
from service.localization.localizers.turned import Weighing, slope_weighed
from service.localization.surface import ContactSurface

SLACK = 30.0
"""Nats below the declared pose within which a box is searched further. A margin, not a
proof: a pose ruled out by more is taken to lose to the declared pose on every comparison
the judge makes, the readings' shared error counted, while it keeps `KEPT` of it."""
KEPT = 20.0
"""Nats of `SLACK` a certificate must still hold for a later declaration: a reading taken
since adds to a pose it ruled out at most what a perfect fit scores, and to the declared
pose what it scores there, so the margin shrinks by the declared pose's shortfall on the
readings since (`Certificate.margin`)."""
ROOT = 0.8
"""Half a root box's side, in step lengths."""
ROOT_TURN = np.deg2rad(8.0)
"""Half a root box's heading range."""
LEAF = 0.15
"""Half a fine box's side, in step lengths."""
LEAF_TURN = np.deg2rad(1.5)
MAX_BOXES = 2_000_000
"""Most boxes a certificate judges; past it (or `MAX_LEAVES`) the map does not rule out
enough, and the certificate holds the declaration back (`Certificate.overflowed`)."""
MAX_LEAVES = 100_000
POLISH = 20
"""Gauss-Newton steps a fine box's centre takes onto the readings."""
RIVALS = 64
"""Most distinct rivals a certificate keeps, best first."""
NEAR = 2.0
"""Rivals within this many times the judge's same-pose tolerance of the declared pose are
its own basin, the spread's to judge: polished from fine boxes 2.5 mm off, poses on
shell:20:40 (seed 5) and terrain:20:40 (seed 3) stopped 2.5 mm and 1-3 degrees from the
leader, 10 nats below it, and held back declarations that were right."""
ROOTS = 64
"""Root boxes a slice of the search takes (a 20 x 20-step map has about 4,500)."""
POLISHED = 512
"""Fine boxes a slice polishes."""
POLISH_WORK = 4
"""A fine box polished costs about as much as this many boxes judged (`Certificate.work`)."""
AGAIN = 8
"""Fine boxes of a slice whose centres' polish fell short (the best of them) polished again
from inside (`_inner_starts`)."""
INNER = np.array([[a, b, c] for a in (-0.5, 0.5) for b in (-0.5, 0.5) for c in (-0.5, 0.5)])
"""Where in a fine box, in its half sides, least squares starts again."""


@dataclass(frozen=True)
class Pyramid:
    """The map's block ranges (`bound_kernels.pyramid`), built once per surface."""

    lo: np.ndarray
    hi: np.ndarray
    steep: np.ndarray
    index: np.ndarray

    @classmethod
    def of(cls, surface: ContactSurface) -> Pyramid:
        pyramid = _PYRAMIDS.get(surface)
        if pyramid is None:
            pyramid = _PYRAMIDS[surface] = cls(*bound_kernels.pyramid(
                surface.centre_heights, surface.map.spacing))
        return pyramid


_PYRAMIDS: weakref.WeakKeyDictionary[ContactSurface, Pyramid] = weakref.WeakKeyDictionary()


@dataclass
class Certificate:
    """A search of the whole map for rivals of one declared pose, on the readings of its
    time (`certify`): its rivals, and whether it ran out of room (then it certifies
    nothing, and the declaration waits)."""

    pose: np.ndarray
    readings: int
    rivals: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    complete: bool = False
    overflowed: bool = False
    boxes: int = 0
    work: int = 0
    """Boxes judged plus `POLISH_WORK` per fine box polished: what a slice of it costs."""
    lead: float = np.nan
    """The declared pose's log likelihood on the certificate's readings (`slope_weighed`)."""

    def margin(self, weighing: Weighing, history: np.ndarray, pose: np.ndarray) -> float:
        """Nats by which every pose the search ruled out still trails `pose` on `history`
        (the certificate's readings and any since): `SLACK`, less `pose`'s shortfall from
        a perfect fit at the least sd on the readings since, and any loss on the rest."""
        since = len(history) - self.readings
        if since < 0 or not np.isfinite(self.lead):
            return -np.inf
        now = float(slope_weighed(weighing, history, pose[np.newaxis], weighing.fit_sd)[0])
        return now - (self.lead - SLACK - since * np.log(weighing.fit_sd))

    def covers(self, weighing: Weighing, history: np.ndarray, pose: np.ndarray,
               kept: float = KEPT) -> bool:
        """Whether this certificate stands for `pose` (within the judge's same-pose
        tolerance) on `history`: complete, and still `kept` nats of margin."""
        return (self.complete
                and bool(within(self.pose[np.newaxis], pose, *weighing.same_pose)[0])
                and self.margin(weighing, history, pose) >= kept)


def certify(weighing: Weighing, history: np.ndarray, pose: np.ndarray, cert: Certificate
            ) -> Iterator[int]:
    """Fill `cert` with every pose on the map that may fit `history` within `SLACK` nats of
    `pose`, found by branch and bound and polished (at most `RIVALS`, not `NEAR` the pose):
    yields the work done, `ROOTS` root boxes or `POLISHED` fine boxes at a time."""
    surface, step = weighing.surface, weighing.step_length
    pose = np.asarray(pose, dtype=np.float64)
    near = (NEAR * weighing.same_pose[0], NEAR * weighing.same_pose[1])
    if surface.map.is_profile:  # the sweep's cells tile a profile's poses exactly
        cert.complete = True    # (`Particles` asks for none there)
        return
    anchor = history[:, :2].mean(axis=0)
    readings = np.ascontiguousarray(history[:, :3], dtype=np.float64)
    readings[:, :2] -= anchor
    reach = np.hypot(readings[:, 0], readings[:, 1])
    sd = weighing.fit_sd
    lead = cert.lead = float(slope_weighed(weighing, history, pose[np.newaxis], sd)[0])
    # the misfit (sum of z^2) a box may have and still hold a pose within SLACK of the
    # leader: the leader's log likelihood counts every reading's -log sd, a box's bound the
    # least sd
    limit = -2.0 * (lead - SLACK) - 2.0 * len(history) * np.log(sd)
    pyramid = Pyramid.of(surface)
    roots, half, half_turn = _roots(surface, step, weighing.margin)
    skip = _anchored(pose, anchor)
    found = []
    for first in range(0, len(roots), ROOTS):
        leaves, boxes, done = bound_kernels.search(
            surface.centre_heights, pyramid.lo, pyramid.hi, pyramid.steep, pyramid.index,
            surface.map.spacing, surface.map.extent, weighing.margin, readings, reach,
            roots[first:first + ROOTS], half, half_turn, LEAF * step, LEAF_TURN, limit, sd,
            weighing.position_sigma, skip, np.array(near), MAX_BOXES - cert.boxes,
            MAX_LEAVES - sum(len(f) for f in found))
        cert.boxes += boxes
        cert.work += boxes
        found.append(leaves)
        yield ROOTS
        if not done:
            cert.overflowed = cert.complete = True
            return
    leaves = np.vstack(found)[:, :3]
    rivals, scores = np.empty((0, 3)), np.empty(0)
    weights = np.ones(len(history))
    for first in range(0, len(leaves), POLISHED):
        boxes = leaves[first:first + POLISHED]
        starts = on_pose_space(surface, unanchored(boxes, anchor))
        polished = gauss_newton(surface, starts, history, weights, iterations=POLISH,
                                max_move=2 * LEAF * step)
        ll = slope_weighed(weighing, history, polished, sd)
        short = np.flatnonzero(ll < lead - SLACK)
        short = short[np.argsort(-ll[short], kind="stable")[:AGAIN]]
        if len(short):  # from a box's centre least squares may stop short of its best
            again = on_pose_space(surface, unanchored(_inner_starts(boxes[short], step),
                                                      anchor))
            tried = gauss_newton(surface, again, history, weights, iterations=POLISH,
                                 max_move=2 * LEAF * step)
            tried_ll = slope_weighed(weighing, history, tried, sd).reshape(-1, len(short))
            best = np.argmax(tried_ll, axis=0)  # corner by corner: row best, column box
            column = np.arange(len(short))
            better = tried_ll[best, column] > ll[short]
            polished[short[better]] = tried[(best * len(short) + column)[better]]
            ll[short[better]] = tried_ll[best, column][better]
            cert.work += POLISH_WORK * len(again)
        keep = (ll >= lead - SLACK) & ~within(polished, pose, *near)
        rivals = np.vstack([rivals, polished[keep]])
        scores = np.concatenate([scores, ll[keep]])
        cert.work += POLISH_WORK * len(starts)
        yield POLISHED
    cert.rivals = rivals[distinct(rivals, scores, *weighing.same_pose)[:RIVALS]]
    cert.complete = True


def _inner_starts(boxes: np.ndarray, step: float) -> np.ndarray:
    """Anchor poses half-way to each corner of every fine box, corner by corner: beside a
    wall the misfit kinks, and from a box's centre least squares stopped short of an exact
    pose inside it (pattern:20:2, seed 0, noise-free, step 31: the truth fitted every
    reading, the fine boxes round it fell at least 63 nats short, and the certificate found
    no rival to a pose a quarter turn off that fitted as well)."""
    half = np.array([LEAF * step, LEAF * step, LEAF_TURN])
    return np.vstack([boxes[:, :3] + corner * half for corner in INNER])


def _roots(surface: ContactSurface, step: float, margin: float
           ) -> tuple[np.ndarray, float, float]:
    """The root boxes (centres: anchor x, y and heading) tiling every pose whose readings'
    centroid lies on the map, and their half side and half heading range."""
    half, half_turn = ROOT * step, ROOT_TURN
    x_max, y_max = surface.map.extent
    xs = np.arange(-margin + half, x_max + margin + half, 2 * half)
    ys = np.arange(-margin + half, y_max + margin + half, 2 * half)
    hs = np.arange(-np.pi + half_turn, np.pi, 2 * half_turn)
    roots = np.array(np.meshgrid(xs, ys, hs, indexing="ij")).reshape(3, -1).T
    return np.ascontiguousarray(roots), half, half_turn


def _anchored(pose: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Where start pose `pose` puts the reading-frame point `anchor`, and its heading."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([pose[0] + c * anchor[0] - s * anchor[1],
                     pose[1] + s * anchor[0] + c * anchor[1], pose[2]])
