"""The grasp-gated policy's turns (paper §6's manipulation): every finger moves together to
turn the object about its centroid in place, bringing contour the fingers could not reach
under them. Each turn is planned under the leading pose (`rolling.plan_turn`) and checked
by the policy's gate at every substep of its rolling motion for every plausible pose
(`rolling.carry_steps`); a mixin of `GraspGatedPolicy`, whose state it reads."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from firmware_if.backend import FingerMove, HandCommand
from service.localization.grasp import hand_quality
from service.localization.localizers.object_tracks import to_object
from service.localization.objects import rolling
from service.localization.policies.hand_view import (
    NOVELTY,
    HandDecision,
    HandView,
    best_allowed,
)
from service.localization.policies.info_gain import information

if TYPE_CHECKING:
    from service.localization.policies.grasp_gated import GraspGatedPolicy


class Turns:
    """Mixed into `GraspGatedPolicy`: its manipulations."""

    def _manipulate(self: GraspGatedPolicy, view: HandView, poses: np.ndarray, weights: np.ndarray,
                    radii: np.ndarray, ambiguous: bool = True) -> HandDecision | None:
        """The best turn in reach that the gate allows (checked best first): by what its
        readings tell of the modes and its `worth`, or, with one mode (not `ambiguous`), by
        its worth alone - the information a turn seems to bring within one mode is mostly
        the spread its own carrying puts between the poses."""
        if any(f.tip_roll is None for f in view.fingers):
            # a turn rolls every tip as planned; a tip with no roll servo would roll (or
            # slide) as the contact makes it, which the motion model does not follow (a
            # held-out five-finger hand without them lost the object's pose at its first
            # turn on the servos, where the simulator had rolled its tips as told)
            return None
        lead = poses[0]
        h, n = len(poses), len(view.fingers)
        s = max(view.sigma, 1e-4)
        weighed = weights > 0  # weightless poses add nothing to the information
        turns: list[tuple[HandDecision, list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]]
        turns, scores = [], []
        for turn in self.turns:
            moves, rolls = rolling.plan_turn(view.field, lead, view.centres, radii, turn,
                                             self.substeps)
            if not all(self._reach(view, f, (view.centres[f] + moves[f])[None])[0]
                       for f in range(n)):
                continue
            tips = np.broadcast_to(view.centres, (h, n, 2))
            states = [(p.copy(), c.copy()) for p, c in rolling.carry_steps(
                view.field, poses, tips, radii, moves, rolls, self.substeps)]
            final_poses, final = states[-1]
            angles = self._turn_angles(view, states)
            if angles is None:
                continue
            gain = float(information(final[weighed].reshape(1, -1, 2 * n), weights[weighed],
                                     s)[0])
            novel = float(np.mean([self._novel(final[:1, f], final_poses[0])
                                   for f in range(n)]))
            precision = self._precision(to_object(final[0], final_poses[0]), radii,
                                        _turn_error(view.motion, turn, self.substeps))
            command = HandCommand(tuple(
                FingerMove(dx=float(m[0]), dz=float(m[1]), roll=float(r))
                for m, r in zip(moves, rolls, strict=True)))
            turns.append((HandDecision(command, "manipulate", None, int(np.sign(turn)),
                                       gain=gain, novel=novel >= 0.5, precision=precision),
                          states, angles))
            scores.append(gain * (ambiguous or not self._precise) + precision + NOVELTY * novel
                          + 1e-3 * abs(turn))  # ties: the larger turn
        quality: dict[int, np.ndarray] = {}

        def allowed(k: int) -> bool:
            quality[k] = self._turn_quality(view, *turns[k][1:])
            return not self.gate or self._safe(
                view, quality[k], weights,
                at_worst=lambda: self._turn_quality(view, *turns[k][1:], worst=True,
                                                    rows=self._counted))

        k = best_allowed(np.array(scores), allowed)
        if k is None:
            return None
        return dataclasses.replace(turns[k][0], predicted_quality=float(quality[k].min()))

    def _turn_angles(self: GraspGatedPolicy, view: HandView,
                     states: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray] | None:
        """Each finger's joint angles (substeps, joints) at every substep of a turn, taken
        from where the leading pose puts its tip; None when out of reach."""
        lead_tips = np.stack([c[0] for _, c in states])  # (substeps, n, 2)
        angles = []
        for f in range(len(view.fingers)):
            ok, q = self._reach(view, f, lead_tips[:, f])
            if not ok:
                return None
            angles.append(q)
        return angles

    def _turn_quality(self: GraspGatedPolicy, view: HandView,
                      states: list[tuple[np.ndarray, np.ndarray]],
                      angles: list[np.ndarray], worst: bool = False,
                      rows: slice | np.ndarray = slice(None)) -> np.ndarray:
        """Least quality over every substep of a turn, per plausible pose (of `rows`; with
        `worst`, at the world's worst: `WorldsWorst`)."""
        if worst:
            return np.min([self._worst.quality(view, p[rows], c[rows],
                                               tuple(q[i] for q in angles))
                           for i, (p, c) in enumerate(states)], axis=0)
        return np.min([hand_quality(view.field, p[rows], c[rows], view.fingers,
                                    tuple(q[i] for q in angles), view.torque, view.grasp)
                       for i, (p, c) in enumerate(states)], axis=0)


def _turn_error(motion: rolling.TwistNoise, turn: float, substeps: int) -> np.ndarray:
    """(3, 3) covariance of the pose error a turn by `turn` radians in `substeps` adds: each
    substep's size strays by `motion.fraction` on its own; a turn about the centroid in place
    moves it little, so its position error is left out."""
    return np.diag([0.0, 0.0, (motion.fraction * turn) ** 2 / substeps])
