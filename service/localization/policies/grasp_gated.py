"""Grasp-gated exploration for a hand (paper §6): learn the most without dropping the object.

Each step either rolls one finger a step along the object while the others hold, or - when
no such move helps - manipulates: every finger works together to turn the object in place,
bringing contour the fingers could not reach under them.

* Options: each finger, either way along the object (the tangent under the leading pose),
  by the step length or a share of it (`STEP_PARTS`).
* Information: for the plausible poses (the heaviest hypotheses), predict where the
  fingertip comes to rest
  (`objects/rolling.settle`) and score the option by the mutual information between that
  reading and the pose (`info_gain.information`), plus a small credit for contour not felt
  yet.
* The gate: the grasp's quality (`grasp.hand_quality`: the disturbance it resists beyond the
  weight) is predicted for every plausible pose at the middle and the end of the move, and
  a move is never taken if the chance that it falls below the threshold exceeds `RISK`
  (or that it comes near the margin, where the object slips, `DROP_RISK`): the chance is
  the posterior weight of the plausible poses under which it would. Near the margin a move
  is also judged at the world's worst (`worlds_worst.py`): a tip near a sharp convex
  corner resting on its vertex and, for two fingers, normals turned by `WORLD_TILT` against the
  grasp and a tip beside a kink resting where it holds least (the model's quality held
  under every plausible pose where the world's dropped the object). Plausible poses are
  the heaviest hypotheses under which the grasp as it is holds the object (it is held).
  While the pose is a continuum the quality spans every level across it, and a rule over
  every sample would forbid every move; the weights say how likely each is. The samples
  leave gaps where an opposed grasp's quality changes fast, so the gate also holds for
  weightless cover poses in those gaps that the readings allow (`guarded_poses.with_cover`), and for
  each plausible mode's spread (`guarded_poses.with_spread`): no move may take one below the
  threshold. Where a tip lies beside a kink of the dilated contour (a hollow narrower than
  the tip, `objects/kinks.py`), the world may rest it on either side or bridging: a pose
  counts as possible (it is held) by the most the grasp may hold there, if the model finds
  it too weak; its moves are weighed against the model's quality, as every pose's are.
  (Judging moves by the least there too was tried: three fingers on blob localized 81 of
  members 0-99 instead of 99, and on a held-out hexagon with one chamfered corner the
  changed path dropped the object. Weighing moves against the most there: 86.) With the
  gate off (the ablation), only reach limits moves.
* Manipulation (`grasp_turns.py`): turns of the object about its centroid in place
  (`rolling.plan_turn` under the leading pose), each checked the same way at every substep
  of its rolling motion for every plausible pose (`rolling.carry`); the safe turn whose
  readings tell most, or that brings the most unfelt contour under the fingers, wins.
  A turn is also taken, if one is safe, once the rolls have stalled: `STALL` of them left
  the modes' shares where they were (`stalled`).
* Precision, for three fingers or more: once one mode is left, a move is also worth what
  its readings would pin the leader's spread by, their shared error and a turn's motion
  error counted (`contour_precision`), and a turn is taken once the rolls are spent
  (`SPENT`): re-reading the same arcs pins nothing new.

* The last resort, for a hand of three fingers or more: with no roll or turn allowed, a roll
  may still take the gate's weightless guards (the spread's neighbours and the cover) below
  the threshold, though not near the margin; likely poses and the chances are held as ever.
  Held at the threshold, guards at the edge of what the start allows (1.06-1.4 N on
  three-finger rounded:23, whose true grasp held 11.6 N) forbade every roll, and 14 of 100
  three-finger rounded runs stopped where they began. Held only off the margin always, not
  only as a last resort, they let 2 of 800 B6 runs drop (three-finger rounded:26, its truth
  at 0.76 N in the world where the model's outline gave 1.18 N; a two-finger keyed). Two
  fingers hold by one opposed pair, whose quality turns on the pose so sharply that the
  truth strays beyond the plausible poses once they explore: with the last resort, the
  least true quality of two fingers on rounded members 200-299 fell to 0.21 N (the margin
  is 0.2 N) from 1.03 N without it.

With nothing safe left to do, the decision says so (`stuck`) and the episode ends undecided.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar

import numpy as np

from firmware_if.backend import FingerMove, HandCommand
from service.localization import chain_kernels
from service.localization.grasp import hand_quality
from service.localization.localizers.object_judge import FRESH
from service.localization.localizers.object_tracks import to_object
from service.localization.localizers.shared_error import correlation_length
from service.localization.objects import kinks, rolling
from service.localization.policies import guarded_poses
from service.localization.policies.contour_precision import ContourSpread
from service.localization.policies.grasp_turns import Turns
from service.localization.policies.hand_view import (
    NOVELTY,
    HandDecision,
    HandView,
    best_allowed,
)
from service.localization.policies.info_gain import information
from service.localization.policies.worlds_worst import WorldsWorst, worlds_worst

FELT = 0.003
"""Metres: contour within this of a felt point counts as felt. Readings closer than the
world's mismatch length share their error, so a mode is pinned down by new stretches of
contour, not by re-reading one; with none left in reach, the hand turns the object."""
SPENT = 0.05
"""Nats of `HandDecision.worth` below which the rolls in reach are spent: then a turn that
pins the leading pose more is taken instead, though a roll may still tell a little. Not
before: a turn begins a new grasp, through which the localizer must carry its tracks (three
fingers on blob:95 turned at the second step, the pool's one mode split after it, and the
run ended undecided, where rolling on localized it in 4 steps)."""
RISK = 0.05
"""Most posterior weight of plausible poses a move may take below the threshold."""
DROP_RISK = 0.005
"""Most posterior weight a move may take within `BUFFER` of the margin, where it slips."""
LIKELY = 0.05
"""Poses holding at least this share of the posterior are likely: the gate holds for each.
(A continuum of poses early on has none: there the chances decide.)"""
RECOVERY = 0.5
"""Nats per threshold's worth of quality a move wins back under the leading pose, while
the grasp there is below twice the threshold: a weak grasp is strengthened first."""
BUFFER = 0.25
"""Share of the gap from the margin to the threshold counted as near the margin."""
TILT = 3.0
"""Sds of the world's slope (`HandView.slope_sd`) by which its outline may turn a contact's
normal from the model's. The start's quality is promised in the world; the model's outline
put it as low as 0.62 of that with two fingers (240 seeded starts, members 0-59 of every
preset) and 0.75 with three, as the quality turns on where the normals point. The best
over every finger's normal turned by three sds (2.4 degrees at B2's mismatch) covered the
world's quality in 237 of the 240 two-finger starts, the rest within 3 %. (Two fingers on
keyed:1, seed 1: the start held 1.03 N in the world and 0.73 N on the model; cut at 1 N on
the model, the truth was not among the poses the gate guards, and the second roll dropped
the object.) Only weighted poses are given the benefit: the gate's weightless neighbours
and cover stand for the poses the readings allow, and at this allowance they forbade every
move from more starts (B6, members 0-99: 241 of 800 runs localized instead of 268)."""
STALL = 6
"""Rolls after which, while modes are left, the rolls count as spent for telling them
apart if the leading mode's share (the localizer's, as log-odds) stayed within
`STALL_LOGIT` across them: a safe turn is taken instead. A roll's predicted information
counts its reading as its own, but the localizer weighs readings from a patch already felt
as sharing the world's error: three fingers on rounded:5 (seed 5) rolled on at a predicted
0.04-0.29 nats a roll, the leader held at 93 % from step 25 to the last, the 60th, and a
safe turn was on offer at each decision a hook printed (steps 17 to 41). Only a leader
holding half or more stalls: among many modes the rolls tell by striking them out, which
the leader's share hardly shows (three fingers on a held-out near circle with one bump
held it at 5-12 % from step 3 to 29, until the bump decided it, 99 % at step 31; turned
at step 12, they ended undecided at step 60). (Asking instead for a new high of
the share, on the localizer's or on the policy's own weights, turned three fingers on
keyed:18 while its leader climbed from 87 to 95 % in seven rolls, and the run ended
undecided, where it had localized.)"""
STALL_LOGIT = 0.3
"""Least change of the leading mode's log-odds over `STALL` rolls that counts as telling
the modes apart (from 93 %: to 91 % or 94.8 %)."""
STEP_PARTS = (1.0, 0.5, 0.25, 0.1)
"""Shares of the step length tried: while the pose is uncertain, only a short roll may be
safe under every plausible pose; as it narrows, longer ones become safe."""


class GraspGatedPolicy(Turns):
    name: ClassVar[str] = "grasp-gated"

    def __init__(self, gate: bool = True, plausible: int = 96, min_gain: float = 0.02,
                 turns: Sequence[float] = (0.2, -0.2, 0.4, -0.4, 0.7, -0.7),
                 substeps: int = 8, precision: bool = True) -> None:
        self.gate, self.plausible, self.min_gain = gate, plausible, min_gain
        self.precision = precision
        """A hand of three fingers or more, once one mode is left, weighs moves by how they
        pin the leader's spread (`contour_precision`) and takes a turn that pins it more
        once the rolls are spent (`SPENT`); otherwise the policy of before: a turn only when
        no roll tells the modes anything. Two fingers keep that: they hold by one opposed
        pair, whose quality turns on the pose so sharply that the truth strays beyond the
        plausible poses as the fingers spread out; weighed by precision, their least true
        quality on rounded, blob and keyed (members 0-19, from a 2 N start) fell to 0.33 N
        from 1.09 N, the margin being 0.2 N, and no more localized (3 of 60). So do
        ambiguous modes: counted there too, three fingers on a helper's held-out outlines
        (a 3:1 rounded rectangle, seed 7; a five-pointed star, seed 16) took other paths
        through their turns and dropped the object where the policy of before did not."""
        self._precise = False
        """`precision` holds for this hand."""
        self.turns, self.substeps = tuple(turns), substeps
        self._felt: list[np.ndarray] = []
        """Object-frame points felt so far (under the leading pose when they were)."""
        self._read: list[np.ndarray] = []
        """Hand-plane fingertip centres read since the last manipulation."""
        self._read_before = np.empty((0, 2))
        """Object-frame centres read before it, under the leading pose as each
        manipulation began (a mode the lead flips to within one grasp moves no reading)."""
        self._read_radii: list[float] = []
        """The radius of the fingertip of each reading, those before first."""
        self._spread: ContourSpread | None = None
        """The leading pose's spread from what was felt (`contour_precision`)."""
        self._lead_mass = 0.0
        """The plausible weight of the leading pose's mode."""
        self._decisions = 0
        self._fresh = 0
        """Readings the localizer has taken since the last manipulation (or the first
        grasp), as its judge counts them: every finger's after a turn, one per roll."""
        self._certified: tuple[np.ndarray, tuple[np.ndarray, ...]] | None = None
        """Centres and joints of the grasp the hand last started from."""
        self._turned = False
        """A manipulation has moved the object: the grasp it ended in is known to keep
        only the threshold, not the first grasp's `GraspSpec.start_quality_n`."""
        self._now = np.empty(0)
        """The grasp's quality as it is, under each plausible pose."""
        self._poses = np.empty((0, 3))
        """The plausible poses of this decision (`_plausible`)."""
        self._counted = np.empty(0, dtype=int)
        """The plausible poses a chance can count: those of a mode or of some weight."""
        self._now_worst: np.ndarray | None = None
        """The grasp's quality as it is at the world's worst (`_worst`), under each of
        `_counted`; computed when first asked."""
        self._worst = WorldsWorst()
        """What the gate fears of the world near the margin, for this hand and object
        (`worlds_worst`)."""
        self._guard = np.empty(0, dtype=bool)
        """Plausible poses that stand for the leader's own spread: no weight of their own,
        but the gate holds for each as for a likely pose."""
        self._mode_of = np.empty(0, dtype=int)
        """Each plausible pose's mode (`guarded_poses.mode_labels`), -1 for none."""
        self._logits: list[float] = []
        """The leading mode's share as log-odds at each decision since the last
        manipulation (`stalled`)."""


    # -- the decision ----------------------------------------------------------------------
    def decide(self, view: HandView) -> HandDecision:
        poses, weights = self._plausible(view)
        if self._decisions == 0:
            self._fresh = len(view.fingers)
        self._decisions += 1
        radii = np.array([f.radius for f in view.fingers])
        lead = poses[0]
        self._remember(view.centres, lead, radii)
        ambiguous = guarded_poses.ambiguous(poses, weights)
        self._precise = (self.precision and len(view.fingers) > 2 and not view.fixed
                         and not ambiguous)
        self._spread = self._spread_now(view, lead) if self._precise else None
        self._lead_mass = float(weights[guarded_poses.in_mode(poses, 0)].sum())
        self._logits.append(_logit(view.mode_mass))
        spent = ambiguous and stalled(self._logits)
        explore = self._explore(view, poses, weights, radii)
        if explore is not None and (view.fixed or not (spent
                                                       or self._may_turn(explore, ambiguous))):
            return self._rolled(explore)
        if not view.fixed:
            turn = self._manipulate(view, poses, weights, radii, ambiguous)
            if turn is not None and (explore is None or spent
                                     or self._turn_instead(explore, turn, ambiguous)):
                self._certified, self._turned = None, True  # it ends in the next start
                self._logits = []
                self._read_before = np.vstack([self._read_before,
                                               to_object(np.asarray(self._read), lead)])
                self._read = []
                self._fresh = len(view.fingers)
                return turn
        if explore is None and self.gate and not view.fixed and len(view.fingers) > 2:
            explore = self._explore(view, poses, weights, radii, last_resort=True)
        return self._rolled(explore) if explore is not None else HandDecision(None, "stuck")

    def _rolled(self, roll: HandDecision) -> HandDecision:
        """`roll`, counted: it adds one reading to those since the last manipulation."""
        self._fresh += 1
        return roll

    def _may_turn(self, explore: HandDecision, ambiguous: bool) -> bool:
        """Whether a turn may do better than the best roll: not while the roll tells the
        modes apart (nor, without `precision`, the one mode's pose, or feels its new
        contour)."""
        if explore.gain >= self.min_gain and (ambiguous or not self._precise):
            return False
        return self._precise or not (explore.novel and not ambiguous)

    def _turn_instead(self, explore: HandDecision, turn: HandDecision,
                      ambiguous: bool) -> bool:
        """Whether to take the best safe `turn` rather than the best roll: the roll tells
        nothing (and feels no new contour of the one mode), or - weighing precision, with
        one mode - the rolls are spent and the turn pins the leader more. Not while one mode
        is left with too few readings since the last turn for the judge to weigh it
        (`object_judge.FRESH`): three fingers on a held-out kidney outline (seed 0) held the
        truth at 100 % from step 2 and turned the object at every one of 100 steps, each
        turn leaving the judge three readings, undeclared."""
        if not ambiguous and self._fresh < FRESH:
            return False
        if explore.gain < self.min_gain and not (explore.novel and not ambiguous):
            return True
        return (self._precise and not ambiguous and explore.worth < SPENT
                and turn.worth > explore.worth)

    def _spread_now(self, view: HandView, lead: np.ndarray) -> ContourSpread:
        """The leading pose's spread from every reading felt so far."""
        sd, length = view.mismatch
        places = np.vstack([self._read_before, to_object(np.asarray(self._read), lead)])
        return ContourSpread.now(view.field, lead, places,
                                 np.asarray(self._read_radii), max(view.sigma, 1e-4), sd,
                                 correlation_length(length), view.step_length)

    def _precision(self, places: np.ndarray, radii: np.ndarray,
                   moved: np.ndarray | None = None) -> float:
        """Nats readings at object-frame `places` would pin the leader by (after a motion of
        error covariance `moved`), times its mode's weight."""
        if not self._precise:
            return 0.0
        assert self._spread is not None
        return self._lead_mass * self._spread.gain(places, radii, moved)

    def _plausible(self, view: HandView) -> tuple[np.ndarray, np.ndarray]:
        """The `plausible` heaviest hypotheses under which the grasp as it is holds the
        object (it is held) and the grasp the hand last started from had the quality known
        of it - its first the start quality (`GraspSpec.start_quality_n`, a promise about
        the world, so judged by the most the grasp could have there: `TILT`), one a
        manipulation ended in the threshold (a manipulation is gated on the model to end in
        one) - with the gate's cover of the gaps between them that hold too."""
        poses, w = view.hypotheses.poses[:self.plausible], view.hypotheses.weights[
            :self.plausible]
        if view.fixed:
            return poses, w / w.sum()
        floor = guarded_poses.spread_floor(view.mismatch[0], view.field.contour.max_radius)
        poses, w, self._guard = guarded_poses.with_spread(poses, w, view.spread, floor)
        if self._certified is None:
            self._certified = (view.centres.copy(), view.joints)
        poses, w, now, start = self._held(view, poses, w)
        if self.gate:  # fill the gaps between the poses that hold, then keep what holds
            cover = guarded_poses.with_cover(view, poses)
            poses, w = np.vstack([poses, cover]), np.concatenate([w, np.zeros(len(cover))])
            self._guard = np.concatenate([self._guard, np.ones(len(cover), dtype=bool)])
            poses, w, now, _ = self._held(view, poses, w, (now, start))
        self._now = now
        self._mode_of = guarded_poses.mode_labels(poses, w)
        self._worst = worlds_worst(view)
        self._counted = np.flatnonzero((self._mode_of >= 0) | (w > 0))
        self._poses, self._now_worst = poses, None
        return poses, w / w.sum()

    def _held(self, view: HandView, poses: np.ndarray, w: np.ndarray,
              known: tuple[np.ndarray, np.ndarray] = (np.empty(0), np.empty(0))
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The poses (and weights, guard mask) under which the grasp holds the object now
        and the grasp the hand last started from had the quality known of it (`_plausible`),
        with the quality now and at that start under each; failing that, those under which
        it holds now; failing that, all. `known` are those qualities for the first poses
        already."""
        assert self._certified is not None
        first = len(known[0])  # the poses whose qualities are new
        rest = poses[first:]
        now = np.concatenate([known[0], self._quality(view, rest, view.centres, view.joints)])
        start = np.concatenate([known[1], self._quality(view, rest, *self._certified)])
        # a turn's end was gated on the model to keep the threshold
        known_start = view.grasp.threshold_n if self._turned else view.grasp.start_quality_n
        # a weighed pose the model finds too weak may be the world's, whose outline turns
        # the normals (the start's promise is the world's: `TILT`) and rests a tip beside a
        # kink anywhere on it: judged by the most it could hold (the policy's moves are
        # still weighed against the model's `now`)
        weighed = w[first:] > 0
        kinked = kinks.any_kinks(view.field.contour, np.array([f.radius for f in view.fingers]))
        tilt = TILT * view.slope_sd if not self._turned else 0.0
        if tilt > 0 or kinked:  # else the most is the model's: nothing to judge again
            weak = first + np.flatnonzero((start[first:] < known_start) & weighed)
            start[weak] = self._quality(view, poses[weak], *self._certified, tilt=tilt,
                                        beside_kinks=kinked)
        held = np.concatenate([np.full(first, np.inf), now[first:]])  # the first held already
        if kinked:
            weak = first + np.flatnonzero((now[first:] < view.grasp.margin_n) & weighed)
            held[weak] = self._quality(view, poses[weak], view.centres, view.joints,
                                       beside_kinks=True)
        for keep in ((held >= view.grasp.margin_n) & (start >= known_start),
                     held >= view.grasp.margin_n):
            if keep.any() and w[keep].sum() > 0:
                self._guard = self._guard[keep]
                return poses[keep], w[keep], now[keep], start[keep]
        return poses, w, now, start

    def _quality(self, view: HandView, poses: np.ndarray, centres: np.ndarray,
                 joints: tuple[np.ndarray, ...], tilt: float = 0.0,
                 beside_kinks: bool = False) -> np.ndarray:
        """Quality under each pose of fingertips at `centres` settled onto it (at best, with
        normals turned by up to `tilt` and, with `beside_kinks`, a tip beside a kink resting where
        it holds most: `grasp.hand_quality`)."""
        return hand_quality(view.field, poses, _settled(view, poses, centres), view.fingers,
                            joints, view.torque, view.grasp, tilt, beside_kinks)

    # -- exploring -------------------------------------------------------------------------
    def _explore(self, view: HandView, poses: np.ndarray, weights: np.ndarray,
                 radii: np.ndarray, last_resort: bool = False) -> HandDecision | None:
        """The best move of one finger that is in reach and safe (`best_allowed`: reach
        and the gate are checked best first, only as far as the choice needs); as a
        `last_resort`, safe with the weightless guards kept only off the margin
        (`_safe`)."""
        n = len(view.fingers)
        _, normals = rolling.contacts(view.field, poses[:1], view.centres[None], radii)
        tangents = np.stack([-normals[0, :, 1], normals[0, :, 0]], axis=-1)
        options = [(f, d, part) for f in range(n) for d in (1, -1) for part in STEP_PARTS
                   if (f, d) not in view.blocked]
        if not options:
            return None
        h = len(poses)
        here = _settled(view, poses, view.centres)  # the fingers that hold, under each pose
        deltas = [d * part * view.step_length * tangents[f] for f, d, part in options]
        targets = [view.centres[f] + delta for (f, _, _), delta in zip(options, deltas,
                                                                      strict=True)]
        weighed = weights > 0  # weightless poses add nothing to the information
        told = np.flatnonzero(weighed | (np.arange(h) == 0))  # and the leader tells novelty

        def aims(k: int, rows: np.ndarray | slice, share: float) -> np.ndarray:
            """Fingertip centres (rows, n, 2) at `share` of move k, settled under poses."""
            f = options[k][0]
            centres = here[rows].copy()
            moved = np.broadcast_to(view.centres[f] + share * deltas[k],
                                    (len(centres), 1, 2)).copy()
            centres[:, f] = rolling.settle(view.field, poses[rows], moved, radii[f:f + 1])[:, 0]
            return centres

        readings = np.stack([aims(k, told, 1.0)[:, f] for k, (f, _, _) in enumerate(options)])
        reach: dict[int, tuple[bool, np.ndarray]] = {}
        quality: dict[int, np.ndarray] = {}

        def reach_of(k: int) -> tuple[bool, np.ndarray]:
            if k not in reach:
                f = options[k][0]
                reach[k] = self._reach(view, f, np.array(
                    [targets[k], view.centres[f] + 0.5 * (targets[k] - view.centres[f])]))
            return reach[k]

        def quality_of(k: int, rows: slice | np.ndarray = slice(None), worst: bool = False
                       ) -> np.ndarray:
            """Least predicted quality over the move's middle and end, per plausible pose
            (with `worst`, at the world's worst: `WorldsWorst`)."""
            if view.fixed:
                return np.full(h, np.inf)[rows]
            if k in quality and not worst:
                return quality[k][rows]
            f = options[k][0]
            angles = reach_of(k)[1]  # (end, middle)
            q = np.minimum(*(self._checkpoint_quality(view, poses[rows], aims(k, rows, share),
                                                      f, angles[1 - part], worst)
                             for part, share in enumerate((0.5, 1.0))))
            if isinstance(rows, slice) and rows == slice(None) and not worst:
                quality[k] = q
            return q

        gated = self.gate and not view.fixed
        s = max(view.sigma, 1e-4)
        gain = information(readings[:, weighed[told]], weights[weighed], s)
        novel = np.array([self._novel(readings[k][:1], poses[0]) for k in range(len(options))])
        larger = np.array([part for _, _, part in options])
        precision = np.array([self._precision(to_object(readings[k][:1], poses[0]),
                                              radii[f:f + 1])
                              for k, (f, _, _) in enumerate(options)])
        score = gain + precision + NOVELTY * novel + 1e-3 * larger  # ties: the longer step
        if gated and self._now[0] < 2 * view.grasp.threshold_n:
            lead_after = np.array([quality_of(k, slice(0, 1))[0] if reach_of(k)[0] else 0.0
                                   for k in range(len(options))])
            score = score + RECOVERY * (lead_after - self._now[0]) / view.grasp.threshold_n
        k = best_allowed(score, lambda k: reach_of(k)[0] and (
            not gated or self._safe(view, quality_of(k), weights, last_resort,
                                    lambda: quality_of(k, self._counted, worst=True))))
        if k is None:
            return None
        f, d, _ = options[k]
        moves: list[FingerMove | None] = [None] * n
        delta = targets[k] - view.centres[f]
        moves[f] = FingerMove(dx=float(delta[0]), dz=float(delta[1]))
        return HandDecision(HandCommand(tuple(moves)), "explore", f, d,
                            float(quality_of(k).min()), float(gain[k]), bool(novel[k]),
                            float(precision[k]))

    def _reach(self, view: HandView, f: int, targets: np.ndarray
               ) -> tuple[bool, np.ndarray]:
        """Whether finger f reaches every target (k, 2), and its joint angles there."""
        finger = view.fingers[f]
        q0 = np.broadcast_to(view.joints[f], (len(targets), len(view.joints[f])))
        spatial = np.column_stack([targets[:, 0], np.zeros(len(targets)), targets[:, 1]])
        q, reached = chain_kernels.inverse(finger, spatial, q0, iterations=100)
        return bool(np.all(reached)), q

    def _checkpoint_quality(self, view: HandView, poses: np.ndarray, centres: np.ndarray,
                            f: int, angles: np.ndarray, worst: bool = False) -> np.ndarray:
        """Quality under each pose of fingertips at `centres` (h, n, 2), finger f at joint
        angles `angles` and the others where they are (with `worst`, at the world's worst:
        `WorldsWorst`)."""
        joints = tuple(angles if i == f else q for i, q in enumerate(view.joints))
        if worst:
            return self._worst.quality(view, poses, centres, joints)
        return hand_quality(view.field, poses, centres, view.fingers, joints, view.torque,
                            view.grasp)

    def _safe(self, view: HandView, quality: np.ndarray, weights: np.ndarray,
              last_resort: bool = False,
              at_worst: Callable[[], np.ndarray] | None = None) -> bool:
        """The gate on a move's predicted quality per plausible pose: under a likely pose
        (the leading modes) never below the threshold, or lower where it already is below;
        the chance (posterior weight) that it takes the quality down below the threshold
        at most `RISK`, and down near the margin at most `DROP_RISK`. The weightless guards
        (`guarded_poses`) are held as likely poses, or, as a `last_resort`,
        only off the margin. `at_worst` gives the move's quality at the world's worst under
        each of `_counted` (`WorldsWorst`): the chance it takes that near the margin, below
        where it is now, is held to `DROP_RISK` too."""
        grasp = view.grasp
        near = grasp.margin_n + BUFFER * (grasp.threshold_n - grasp.margin_n)
        worse = quality < self._now  # only what the move itself costs counts
        likely = weights >= LIKELY  # weights sum to one
        floor = np.full(len(weights), grasp.threshold_n)
        if len(self._guard) == len(weights):
            if last_resort:
                floor[self._guard & ~likely] = near
            likely |= self._guard
        if not (np.all((quality >= floor) | ~worse | ~likely)
                and weights[worse & (quality < grasp.threshold_n)].sum() <= RISK
                and self._near_margin_chance(worse & (quality < near), weights) <= DROP_RISK):
            return False
        if at_worst is None or not self._worst.feared:
            return True
        worst, near_worst = at_worst(), np.zeros(len(weights), dtype=bool)
        near_worst[self._counted] = (worst < self._worst_now(view)) & (worst < near)
        return self._near_margin_chance(near_worst, weights) <= DROP_RISK

    def _worst_now(self, view: HandView) -> np.ndarray:
        """`_now_worst`, computed the first time a decision asks."""
        if self._now_worst is None:
            poses = self._poses[self._counted]
            self._now_worst = self._worst.quality(view, poses,
                                                  _settled(view, poses, view.centres),
                                                  view.joints)
        return self._now_worst

    def _near_margin_chance(self, near: np.ndarray, weights: np.ndarray) -> float:
        """The chance a move takes the grasp near the margin: the whole weight of every
        mode one of whose poses it takes there (`guarded_poses.mode_labels`), and that of
        poses of no mode. A mode's poses are samples of one continuous uncertainty, over which the
        quality can fall steeply (a star's flank: three fingers on a held-out five-pointed
        star, seed 37, moved where the two poses beside the truth predicted 0.24 and
        0.19 N at 0.15 % of the weight between them, the mode holding 17 %; the truth fell
        to 0.18 N and the object dropped)."""
        labels = self._mode_of if len(self._mode_of) == len(weights) else np.full(
            len(weights), -1)
        hit = np.unique(labels[near & (labels >= 0)])
        return float(weights[np.isin(labels, hit) | (near & (labels < 0))].sum())

    # -- felt contour ----------------------------------------------------------------------
    def _remember(self, centres: np.ndarray, lead: np.ndarray, radii: np.ndarray) -> None:
        self._felt.extend(to_object(centres, lead))
        self._read.extend(centres)
        self._read_radii.extend(float(r) for r in radii)

    def _novel(self, centre: np.ndarray, pose: np.ndarray) -> float:
        """1 if the fingertip at `centre` (1, 2) under `pose` is on contour not felt yet."""
        if not self._felt:
            return 1.0
        local = to_object(centre, pose)[0]
        felt = np.asarray(self._felt)
        return float(np.min(np.hypot(*(felt - local).T)) > FELT)


def stalled(logits: Sequence[float]) -> bool:
    """Whether the last `STALL` rolls left the leading mode's share where it was: its
    log-odds at the decision before them and after each within `STALL_LOGIT`, the leader
    holding half or more throughout."""
    recent = np.asarray(logits[-STALL - 1:], dtype=np.float64)
    return bool(len(recent) > STALL and np.all(np.isfinite(recent))
                and np.all(recent >= 0.0) and np.ptp(recent) < STALL_LOGIT)


def _logit(share: float) -> float:
    """Log-odds of a share (NaN stays NaN): equal steps in it are equal evidence, near 50 %
    and near 100 % alike."""
    p = min(max(share, 1e-9), 1 - 1e-9)
    return float(np.log(p / (1 - p))) if np.isfinite(share) else float("nan")


def _settled(view: HandView, poses: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Fingertips at `centres` (n, 2) settled onto the object under each pose: (B, n, 2)."""
    radii = np.array([f.radius for f in view.fingers])
    return rolling.settle(view.field, poses,
                          np.broadcast_to(centres, (len(poses), *np.shape(centres))).copy(),
                          radii)
