"""The paper's exploration heuristic (§4.2): move where a few candidates disagree most.

Sample 10 candidates, predict the height each compass move would give under each, and
take the move whose predictions spread most (largest standard deviation); a move found
blocked is skipped for the next best.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from service.localization.policies.base import PolicyInput, allowed_moves, predicted_heights


class PaperPolicy:
    name: ClassVar[str] = "paper"

    def __init__(self, samples: int = 10) -> None:
        self.samples = samples

    def next_move(self, view: PolicyInput) -> int:
        poses, weights = view.hypotheses.poses, view.hypotheses.weights
        moves = allowed_moves(view)
        if len(poses) == 0 or not np.any(weights > 0):
            return moves[int(view.rng.integers(len(moves)))]
        k = min(self.samples, int(np.count_nonzero(weights)))
        picked = view.rng.choice(len(poses), size=k, replace=False, p=weights / weights.sum())
        z, inside = predicted_heights(view, poses[picked])
        z = np.where(inside, z, np.nan)
        with np.errstate(invalid="ignore"):
            spread = np.array([np.nanstd(z[m]) if inside[m].any() else -1.0 for m in range(4)])
        return max(moves, key=lambda m: spread[m])


class RandomPolicy:
    """A uniformly random unblocked move: the baseline every policy should beat."""

    name: ClassVar[str] = "random"

    def next_move(self, view: PolicyInput) -> int:
        moves = allowed_moves(view)
        return moves[int(view.rng.integers(len(moves)))]
