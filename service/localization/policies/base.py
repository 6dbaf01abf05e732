"""The exploration-policy contract: given the hypotheses, choose the next compass move."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from service.localization.localizers.base import Estimate, Hypotheses
from service.localization.models import rotate
from service.localization.surface import ContactSurface

MOVES = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
"""The finger's own compass directions (+x, +y, -x, -y), as unit vectors in its frame."""
MOVE_NAMES = ("+x", "+y", "-x", "-y")


@dataclass(frozen=True)
class PolicyInput:
    """What a policy may look at when choosing a move."""

    hypotheses: Hypotheses
    displacement: np.ndarray
    """The finger's measured (dx, dy) since first contact, in its frame."""
    blocked: frozenset[int]
    """Moves already found blocked from where the finger is now."""
    surface: ContactSurface
    step_length: float
    rng: np.random.Generator
    walls: bool = False
    """Whether the map's edge is what blocks a step, so a blocked step is evidence."""
    estimate: Estimate | None = None
    """The localizer's current belief: its leading pose and that pose's spread."""
    planar: bool = False
    """The finger moves in its plane only (a planar finger's chain): it has no +-y step, on
    a map too (a held-out lab's planar finger on `peaks` spent 36 of 100 steps on +-y
    moves, every one blocked)."""

    @property
    def along_x_only(self) -> bool:
        """Whether the finger steps only along its own x: on a profile, or planar."""
        return self.planar or self.surface.map.is_profile


class Policy(Protocol):
    name: ClassVar[str]

    def next_move(self, view: PolicyInput) -> int:
        """Index into MOVES of the next step."""


def allowed_moves(view: PolicyInput) -> list[int]:
    """Moves not known to be blocked; along x only on a profile or for a planar finger."""
    candidates = [0, 2] if view.along_x_only else [0, 1, 2, 3]
    free = [m for m in candidates if m not in view.blocked]
    return free or candidates


def predicted_heights(view: PolicyInput, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative centre height after each move for each pose: (4, N) heights and inside mask.

    Heights are relative to each pose's own first contact, as the finger would measure them.
    """
    targets = view.displacement[np.newaxis, :] + MOVES * view.step_length  # (4, 2)
    dx, dy = rotate(poses[np.newaxis, :, 2], targets[:, 0:1], targets[:, 1:2])
    x, y = poses[np.newaxis, :, 0] + dx, poses[np.newaxis, :, 1] + dy
    z, inside = view.surface.lookup(x, y)
    z0, _ = view.surface.lookup(poses[:, 0], poses[:, 1])
    return z - z0[np.newaxis, :], inside
