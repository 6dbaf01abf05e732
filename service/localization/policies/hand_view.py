"""What the grasp-gated policy looks at and what it decides (`grasp_gated.py`), and how it
picks the best option a check allows: shared by its rolls and its turns (`grasp_turns.py`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from firmware_if.backend import HandCommand
from firmware_if.hand import Finger
from service.localization.grasp import GraspSpec
from service.localization.localizers.base import Hypotheses
from service.localization.objects import rolling
from service.localization.objects.field import ContactField

NOVELTY = 0.05
"""Nats credited to a move whose fingertip lands on contour not felt yet."""

@dataclass(frozen=True)
class HandView:
    """What the policy may look at."""

    hypotheses: Hypotheses
    centres: np.ndarray
    """(n, 2) every fingertip centre now."""
    joints: tuple[np.ndarray, ...]
    """Joint angles of each finger now."""
    field: ContactField
    fingers: tuple[Finger, ...]
    torque: float
    """N m each joint pushes with (goal current times torque per ampere)."""
    grasp: GraspSpec
    step_length: float
    sigma: float
    """Reading noise (metres) the localizer assumes."""
    fixed: bool = False
    """The object is clamped: nothing to drop, nothing to manipulate."""
    blocked: frozenset[tuple[int, int]] = field(default_factory=frozenset)
    """(finger, direction) moves found out of reach from here."""
    spread: tuple[float, float] = (0.0, 0.0)
    """The leading pose's own uncertainty (position sd in metres, heading sd in radians)."""
    mode_mass: float = float("nan")
    """The localizer's share of its leading mode (`Estimate.mode_mass`); NaN before it has
    one."""
    slope_sd: float = 0.0
    """Sd (radians) of the slope by which the world's outline differs from the model's
    (`NoiseSpec.surface_slope_sd`); 0: the model is the world."""
    motion: rolling.TwistNoise = rolling.EXACT
    """How a carried object's motion strays from the rolling model (`HandSettings`' B2 step
    noise): what a turn adds to the leading pose's spread."""
    mismatch: tuple[float, float] = (0.0, 0.0)
    """Sd and correlation length (metres) of the world's outline's difference from the
    model's (`NoiseSpec.surface_sigma`, `surface_correlation`): readings near each other
    share it (`contour_precision`)."""


@dataclass(frozen=True)
class HandDecision:
    command: HandCommand | None
    kind: str
    """'explore', 'manipulate', or 'stuck' (no safe move: the episode ends)."""
    finger: int | None = None
    direction: int = 0
    predicted_quality: float = float("nan")
    """Least quality predicted over the plausible poses along the move (newtons)."""
    gain: float = 0.0
    """Expected information (nats) of the move's readings about the pose."""
    novel: bool = False
    """The move feels contour not felt yet."""
    precision: float = 0.0
    """Nats by which the move's readings would shrink the leading pose's spread, their
    shared error counted (`contour_precision`), times the leading mode's weight."""

    @property
    def worth(self) -> float:
        """What the move is worth to the one mode there is: how it pins the leader's spread,
        and a credit for new contour."""
        return self.precision + NOVELTY * self.novel


def best_allowed(score: np.ndarray, allowed: Callable[[int], bool]) -> int | None:
    """`np.argmax` of `score` over the indices `allowed` accepts (NaN counts highest; ties:
    the lower index), asking `allowed` best first and only until one passes: reach and the
    gate cost most of a decision, and the best option is usually allowed."""
    nan = np.isnan(score)
    rest = np.flatnonzero(~nan)
    for k in np.concatenate([np.flatnonzero(nan), rest[np.argsort(-score[rest], kind="stable")]]):
        if allowed(int(k)):
            return int(k)
    return None
