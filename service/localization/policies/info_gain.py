"""Information-gain exploration that plans ahead: go where the hypotheses disagree most.

For the leading hypotheses (weighted), predict the relative height a reading would give;
the expected information of a reading is the mutual information between it and which
hypothesis is true. With Gaussian reading noise it has a closed pairwise form (the expected
log of the predictive density; Huber et al.'s lower bound):

    I = -sum_i w_i log sum_j w_j exp(-(z_i - z_j)^2 / (4 s^2))

One step rarely suffices where it matters most. On a plain every neighbour reads the same
under every hypothesis, and the feature that would decide between them lies several steps
away; a one-step policy wanders there (the paper: "a more long-term decision-making
algorithm could possibly improve this problem"). So each decision scores every place within
`reach` steps (a diamond of lattice points in the finger's frame) by the information of a
reading there, per step of the route to it, and walks toward the best; it re-plans after
every reading, and keeps its target unless another is clearly better, so it never dithers
between two. Once one mode leads, a reading is also worth what it would shrink the
leading pose's spread by, the spread as the declaration weighs it: nearby readings share
the map's error (`precision.Spread`). Places not read yet earn a little credit (`NOVELTY`):
where the hypotheses agree, new places still add the evidence a declaration needs, where
shuttling between two read places adds none.

When the place that tells the main modes apart at the best rate per step lies beyond
`reach` (four alike holes, whose quarter turns differ only at the one corner that breaks
the pattern), and beats every place in reach by `FAR_GAIN`, a far search walks there,
`far_reach` steps out at most, until it is read or tells them apart no more
(`_far_target`).

Where the map's edge is what blocks a step (`PolicyInput.walls`), a hypothesis that puts a
place off the map predicts a blocked step there: an outcome of its own, which the
localizers use as evidence, so it counts as information. Elsewhere a blocked step tells
nothing, and is predicted as a reading of where the finger stands. Moves found blocked
from here are never taken again.

The work per decision is bounded: the one-step scores use at most `samples` hypotheses,
the plan at most `modes` distinct ones over at most 2 reach (reach + 1) + 1 places, the far
search at most `FAR_MODES` over 2 far_reach (far_reach + 1) + 1.
"""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Iterable
from typing import ClassVar

import numpy as np

from service.localization import kernels
from service.localization.localizers.pool import niche
from service.localization.models import rotate
from service.localization.policies.base import MOVES, PolicyInput, allowed_moves
from service.localization.policies.precision import Spread

NOVELTY = 0.05
"""Information (nats) credited to a reading at a place not read yet."""
REREAD = 0.25
"""Share of its information a reading at a place already read is credited with: the
localizer has weighed the hypotheses there once, so what they still disagree on there is
mostly within the noise."""
TRIVIAL = 0.01
"""Information (nats) below which a reading counts as telling nothing: hypotheses that
differ by less are one mode, and chasing their differences makes a policy dither."""
BLOCKED = 1.0
"""The predicted "reading" of a blocked step, metres: far from any height, so it stands
apart from every real reading."""
KEEP_TARGET = 1.5
"""A new target must promise this many times the rate of the current one to replace it."""
FAR_MODES = 8
"""Most modes the far search (`_far_target`) tells apart."""
MAIN_SHARE = 0.5
"""Share of the leader's weight a mode needs to count as a main mode in the far search."""
FAR_GAIN = 2.0
"""How many times the rate (information per step) of the best place in reach a far place
must promise for the far search to walk there instead."""
OFF_MAP = 0.01
"""Least chance of lying on the map at which a move along a route is taken while another
on it has more: walking along the map's edge to a far corner, a finger whose frame lay 23
degrees to the edge tried the step over it at every other place, every pose predicting it
blocked, and lost 5 of 21 steps (pattern:20:1, seed 2, B2's noise)."""
MAIN_CELL = (2.0, np.deg2rad(30.0))
"""Steps and radians apart that two poses are distinct main modes: poses a fraction of a
step apart differ at every edge in reach, and telling them apart is the plan's job, not a
reason to walk away."""


class InfoGainPolicy:
    name: ClassVar[str] = "info-gain"

    def __init__(self, samples: int = 200, reach: int = 6, modes: int = 32,
                 noise_floor: float = 0.015, far_reach: int = 24) -> None:
        kernels.warm_up()  # compile before the first decision, not during it
        self.samples = samples
        self.reach = reach
        self.modes = modes
        self.far_reach = far_reach
        """Steps (Manhattan) out to which the far search looks (`_far_target`)."""
        self.noise_floor = noise_floor
        """Smallest reading sd assumed, as a fraction of the step: hypotheses closer than
        this are treated as one, so a noise-free run does not chase negligible differences."""
        self._walls: set[tuple[int, int, int]] = set()
        """(place, move) pairs found blocked this episode, never tried again."""
        self._reads: Counter[tuple[int, int]] = Counter()
        """Readings taken at each place (lattice point) this episode."""
        self._unreachable: set[tuple[int, int]] = set()
        """Places found walled off (a far target no free move led to): never targets
        again. So is every place beyond a blocked step (`_out_of_reach`)."""
        self._target: tuple[int, int] | None = None
        self._far: tuple[int, int] | None = None
        """The place the far search walks to (`_far_target`)."""
        self._positions: list[np.ndarray] = []
        """Where (finger frame) every reading so far was taken: readings near each other
        share the map's error, which `precision.Spread` counts."""

    def next_move(self, view: PolicyInput) -> int:
        here = _place(view.displacement, view.step_length)
        self._reads[here] += 1
        self._positions.append(np.asarray(view.displacement, dtype=np.float64)[:2].copy())
        for m in view.blocked:
            self._walls.add((*here, m))
        moves = self._moves(view, here)
        poses, weights = view.hypotheses.poses, view.hypotheses.weights
        if len(poses) == 0:
            return moves[0]
        s = self.noise_floor * view.step_length
        spread = Spread.now(view, s, self._positions)
        far = self._far_target(view, here, poses, weights, s)
        if far is not None and not _route(moves, here, far):  # walled off from here
            self._unreachable.add(far)
            far = self._far = None
        if far is not None:  # a place beyond reach tells the main modes apart far faster
            self._target = far
            return self._toward(view, here, far, moves, poses, weights, s, spread)
        offsets = _diamond(self.reach, view.along_x_only)
        value = self._value(view, poses, weights, offsets, s, spread)
        dist = np.abs(offsets).sum(axis=1)
        reachable = self._reachable(here, offsets)
        rate = np.where((dist > 0) & reachable, value / np.maximum(dist, 1), -np.inf)
        best = int(np.argmax(rate))
        target = (here[0] + int(offsets[best, 0]), here[1] + int(offsets[best, 1]))
        if not rate[best] > 0:  # nothing in reach tells anything: to the nearest new place
            target = self._nearest_unread(here, view.along_x_only) or target
        if self._target is not None and self._target != here:
            kept = np.flatnonzero((offsets[:, 0] == self._target[0] - here[0])
                                  & (offsets[:, 1] == self._target[1] - here[1]))
            if len(kept) and reachable[kept[0]] and rate[best] < KEEP_TARGET * rate[kept[0]]:
                target = self._target
        self._target = target
        return self._toward(view, here, target, moves, poses, weights, s, spread)

    # -- scoring ---------------------------------------------------------------------------
    def _value(self, view: PolicyInput, poses: np.ndarray, weights: np.ndarray,
               offsets: np.ndarray, s: float, spread: Spread | None) -> np.ndarray:
        """Information of a reading at each place (plus novelty), over distinct modes."""
        keep = niche(poses, weights, 0.5 * view.step_length, np.deg2rad(15.0),
                     limit=self.modes)
        p, w = poses[keep], weights[keep] / weights[keep].sum()
        z, inside = _readings(view, p, offsets)
        info = information(z[:, :, np.newaxis], w, s) if len(p) > 1 else np.zeros(len(z))
        here = _place(view.displacement, view.step_length)
        reads = np.array([self._reads[(here[0] + int(i), here[1] + int(j))]
                          for i, j in offsets])
        precision = np.zeros(len(offsets)) if spread is None else spread.gain(view, offsets)
        return _credit(info, precision, (reads == 0) * (inside @ w), reads == 1)

    def _far_target(self, view: PolicyInput, here: tuple[int, int], poses: np.ndarray,
                    weights: np.ndarray, s: float) -> tuple[int, int] | None:
        """Where to go when the unread place within `far_reach` that tells the main modes
        apart at the best rate per step of the way lies beyond reach and promises
        `FAR_GAIN` times the best rate in reach: that place, kept until it is read or tells
        them apart no more. Four alike holes that one chamfered
        corner tells apart leave every place near the finger alike under the pattern's
        quarter turns, and the corner lies farther than the plan looks (pattern:20:0,
        seeds 3, 5, 7: 60 steps near the start, the pose pinned to 0.2 mm, its turns
        equally likely), while small modes that differ in reach keep the plan busy; once
        the corner is in reach, those small modes led the plan away again. The main modes:
        distinct ones holding at least `MAIN_SHARE` of the leader's weight, at most
        `FAR_MODES`. A place in reach that tells them apart a little does not keep the
        finger near: eight alike pockets (pattern:20:1, seed 4) kept the plan in reach busy
        for 32 steps while the places that halve the modes lay farther out. None with one
        main mode, when the best rate is in reach or not twice beaten beyond it (and no
        place is being walked to), or when no place within `far_reach` tells them apart."""
        keep = niche(poses, weights, MAIN_CELL[0] * view.step_length, MAIN_CELL[1],
                     limit=FAR_MODES)
        keep = keep[weights[keep] >= MAIN_SHARE * weights[keep].max()]
        if len(keep) < 2:
            self._far = None
            return None
        p, w = poses[keep], weights[keep] / weights[keep].sum()
        profile = view.along_x_only

        def telling(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Mask of the places (offsets from here), unread and not known out of reach,
            where a reading tells the main modes apart, and its information there."""
            z, _ = _readings(view, p, offsets)
            info = information(z[:, :, np.newaxis], w, s)
            places = offsets + np.array(here)
            fresh = ~_among(places, self._reads.keys()) & ~self._out_of_reach(places)
            return (info >= TRIVIAL) & fresh & (np.abs(offsets).sum(axis=1) > 0), info

        if self._far is not None:  # walking to one: on while it still tells them apart
            if telling(np.array([self._far]) - np.array(here))[0][0]:
                return self._far
            self._far = None
        near = _diamond(self.reach, profile)
        mask, info = telling(near)
        best_near = float(np.max(info[mask] / np.abs(near[mask]).sum(axis=1), initial=0.0))
        # no reading tells more than the main modes' entropy, so no place farther out than
        # that over FAR_GAIN times the best rate in reach can beat it: look no farther
        horizon = self.far_reach if best_near == 0 else min(
            self.far_reach, int(-np.sum(w * np.log(w)) / (FAR_GAIN * best_near)))
        offsets = _diamond(horizon, profile)
        dist = np.abs(offsets).sum(axis=1)
        offsets, dist = offsets[dist > self.reach], dist[dist > self.reach]  # beyond reach
        if len(offsets) == 0:
            return None
        mask, info = telling(offsets)
        rate = np.where(mask, info / dist, -np.inf)
        best = int(np.argmax(rate))
        if not (mask[best] and rate[best] >= FAR_GAIN * best_near):
            return None  # the plan in reach will do
        self._far = (here[0] + int(offsets[best, 0]), here[1] + int(offsets[best, 1]))
        return self._far

    def _reachable(self, here: tuple[int, int], offsets: np.ndarray) -> np.ndarray:
        """Mask of the places (offsets from `here`) not known to be out of reach."""
        return ~self._out_of_reach(offsets + np.array(here))

    def _out_of_reach(self, places: np.ndarray) -> np.ndarray:
        """Mask of the places (n, 2) known out of reach: walled off, or on the line beyond
        a blocked step, however far (the map and the workspace are convex enough). Marked
        only so far out, a planar finger at its workspace's limit took the first place
        past the mark for the nearest unread one and shuttled between the last two places
        before the limit for 20 steps on the bus emulator (seed 0)."""
        out = _among(places, self._unreachable)
        for i, j, m in self._walls:
            d = MOVES[m].astype(np.int64)
            offset = places - np.array([i, j])
            out |= (offset[:, 0] * d[1] == offset[:, 1] * d[0]) & (offset @ d > 0)
        return out

    def _toward(self, view: PolicyInput, here: tuple[int, int], target: tuple[int, int],
                moves: list[int], poses: np.ndarray, weights: np.ndarray, s: float,
                spread: Spread | None) -> int:
        """The free move along a shortest route to `target` whose own reading tells most;
        any free move if none leads there."""
        options = _route(moves, here, target) or moves
        if len(options) == 1:
            return options[0]
        k = min(self.samples, len(poses))
        top = np.argsort(-weights, kind="stable")[:k]
        w = weights[top] / weights[top].sum()
        steps = MOVES[options].astype(np.int64)
        z, inside = _readings(view, poses[top], steps)
        gain = (information(z[:, :, np.newaxis], w, s) if k > 1 else np.zeros(len(options)))
        reads = np.array([self._reads[(here[0] + int(MOVES[m][0]), here[1] + int(MOVES[m][1]))]
                          for m in options])
        precision = np.zeros(len(steps)) if spread is None else spread.gain(view, steps)
        on_map = inside @ w
        value = _credit(gain, precision, (reads == 0) * on_map, reads == 1)
        if on_map.max() >= OFF_MAP:  # not into the edge where every likely pose has it
            value = np.where(on_map < OFF_MAP, -np.inf, value)
        return options[int(np.argmax(value))]

    def _nearest_unread(self, here: tuple[int, int], profile: bool
                        ) -> tuple[int, int] | None:
        """The nearest place not read yet and not known unreachable, at any distance: once
        every place in reach has been read, the finger shuttled between the last two (a
        planar finger at the map's edge, its unread places 7 steps away)."""
        offsets = _diamond(16 * self.reach, profile)
        places = offsets[np.argsort(np.abs(offsets).sum(axis=1), kind="stable")] + np.array(here)
        open_ = np.flatnonzero(~_among(places, self._reads.keys()) & ~self._out_of_reach(places))
        return None if len(open_) == 0 else (int(places[open_[0], 0]), int(places[open_[0], 1]))

    def _moves(self, view: PolicyInput, here: tuple[int, int]) -> list[int]:
        """Allowed moves minus those found blocked from here."""
        moves = allowed_moves(view)
        free = [m for m in moves if (*here, m) not in self._walls]
        return free or moves


def _credit(info: np.ndarray, precision: np.ndarray, novel: np.ndarray, once: np.ndarray
            ) -> np.ndarray:
    """What a reading is worth. At a new place: what it tells the modes apart by, what it
    pins the leading pose by, and `NOVELTY` times the chance that the place is on the map.
    At a place read once: a share of the first only. The map errs there as it did the
    first time, so a second reading cannot pin the pose any better (the localizer counts
    it as the same place); crediting that drew a planar finger on hardware into reading
    the same two places for fifty steps. At a place read twice or more: nothing (the same
    two places, each read again for want of better, were a planar finger's last 30 steps
    on the bus emulator)."""
    info = np.where(info < TRIVIAL, 0.0, info)
    return np.where(novel > 0, info + precision + NOVELTY * novel,
                    np.where(once, REREAD * info, 0.0))


def _place(displacement: np.ndarray, step: float) -> tuple[int, int]:
    """The lattice point (in steps, finger frame) nearest the finger's displacement."""
    i, j = np.round(np.asarray(displacement, dtype=np.float64)[:2] / step)
    return int(i), int(j)


def _route(moves: list[int], here: tuple[int, int], target: tuple[int, int]) -> list[int]:
    """The moves among `moves` that bring the finger closer to `target`."""
    di, dj = target[0] - here[0], target[1] - here[1]
    return [m for m in moves if (MOVES[m][0] * di > 0) or (MOVES[m][1] * dj > 0)]


def _among(places: np.ndarray, known: Iterable[tuple[int, int]]) -> np.ndarray:
    """Mask of the places (n, 2) that are in `known`."""
    known = np.array(list(known), dtype=np.int64).reshape(-1, 2)
    if len(known) == 0:
        return np.zeros(len(places), dtype=bool)
    key = 1 << 32
    return np.isin(places[:, 0].astype(np.int64) * key + places[:, 1],
                   known[:, 0] * key + known[:, 1])


@functools.lru_cache(maxsize=16)
def _diamond(reach: int, profile: bool) -> np.ndarray:
    """Lattice offsets (n, 2) within `reach` steps (Manhattan); along x only on a profile."""
    r = np.arange(-reach, reach + 1)
    if profile:
        out = np.column_stack([r, np.zeros_like(r)])
    else:
        i, j = np.meshgrid(r, r, indexing="ij")
        near = np.abs(i) + np.abs(j) <= reach
        out = np.column_stack([i[near], j[near]])
    out.flags.writeable = False  # cached: shared by every caller
    return out


def _readings(view: PolicyInput, poses: np.ndarray, offsets: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Relative height each pose (N) predicts at each place (T, offsets in steps from
    here), (T, N), and whether the place is on the map. A place off the map predicts a
    blocked step: `BLOCKED` where the edge blocks, else the height where the finger stands
    (nothing new)."""
    step = view.step_length
    targets = (np.asarray(view.displacement, dtype=np.float64)[np.newaxis, :2]
               + offsets * step)
    dx, dy = rotate(poses[np.newaxis, :, 2], targets[:, 0:1], targets[:, 1:2])
    z, inside = view.surface.lookup(poses[np.newaxis, :, 0] + dx, poses[np.newaxis, :, 1] + dy)
    hx, hy = rotate(poses[:, 2], view.displacement[0], view.displacement[1])
    both, _ = view.surface.lookup(np.concatenate([poses[:, 0] + hx, poses[:, 0]]),
                                  np.concatenate([poses[:, 1] + hy, poses[:, 1]]))
    z0 = both[len(poses):]
    here = both[:len(poses)] - z0
    blocked = BLOCKED if view.walls else here[np.newaxis, :]
    return np.where(inside, z - z0[np.newaxis, :], blocked), inside.astype(np.float64)


def information(readings: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    """Mutual information (nats) between hypothesis and reading, per option.

    `readings` is (options, N, D): the D readings each of N hypotheses predicts. The
    pairwise sum is a compiled loop (`kernels.information`): as a (options, N, N, D)
    array it took 11 ms a decision at N = 200, ten times the localizer's update.
    """
    return kernels.information(np.ascontiguousarray(readings, dtype=np.float64),
                               np.ascontiguousarray(weights, dtype=np.float64), float(sigma))
