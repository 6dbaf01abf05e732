"""What the world may make of a grasp beyond the model's quality, as the grasp gate fears it
near the margin (`grasp_gated.GraspGatedPolicy._safe`).

The model's outline differs from the world's by a fraction of a millimetre. Where the grasp's
quality turns on that - the normals' directions for an opposed pair, a tip beside a hollow
narrower than itself, a tip near a sharp corner - the model can hold a grasp the world drops.
Near the margin, a move is also judged at the least the world may make of it
(`grasp.hand_quality` with `least`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from service.localization.grasp import hand_quality
from service.localization.objects import corners, kinks

if TYPE_CHECKING:
    from service.localization.policies.grasp_gated import HandView

WORLD_TILT = 1.0
"""Sds of the world's slope by which the gate's check near the margin turns each contact's
normal against the grasp (the least over the ways, `grasp.hand_quality`). Two fingers on a
held-out 3:1 rounded rectangle, seed 27: the truth itself predicted 0.21 N after a roll,
-0.07 N with one normal turned one sd (0.8 degrees), and the world dropped the object at
-0.18 N; no plausible pose came near the margin. Measured only near the margin: the
threshold's checks stay the model's, whose every allowance cost starts
(`grasp_gated.TILT`)."""


@dataclass(frozen=True)
class WorldsWorst:
    """What the world may make of a grasp beyond the model's quality, as the gate fears it
    near the margin (`grasp.hand_quality` with `least`)."""

    tilt: float = 0.0
    """Radians each contact's normal may turn against the grasp (`WORLD_TILT` sds of the
    world's slope)."""
    kinks: bool = False
    """A tip beside a kink may rest on either side or bridging (`objects/kinks.py`)."""
    corners: bool = False
    """A tip near a sharp convex corner may rest on its vertex (`objects/corners.py`)."""

    @property
    def feared(self) -> bool:
        return self.tilt > 0 or self.kinks or self.corners

    def quality(self, view: HandView, poses: np.ndarray, centres: np.ndarray,
                joints: tuple[np.ndarray, ...]) -> np.ndarray:
        """Quality under each pose of fingertips at `centres` (B, n, 2), at this worst."""
        return hand_quality(view.field, poses, centres, view.fingers, joints, view.torque,
                            view.grasp, self.tilt, self.kinks, least=True,
                            beside_corners=self.corners)


def worlds_worst(view: HandView) -> WorldsWorst:
    """What the gate fears of the world near the margin. Two fingers, which hold by one
    opposed pair whose quality turns on the normals sharply: normals turned by
    `WORLD_TILT`, a tip beside a kink on either side, a tip near a sharp corner on its
    vertex. Three fingers or more fear only the corners: judged at the tilt and the
    kinks too, on a helper's ten held-out outlines (40 runs each) they localized 154
    instead of 163, and dropped one object the model's judgement held (a rounded
    triangle, seed 27, at step 60)."""
    radii = np.array([f.radius for f in view.fingers])
    sharp = corners.any_corners(view.field.contour)
    if len(view.fingers) != 2:
        return WorldsWorst(corners=sharp)
    return WorldsWorst(tilt=WORLD_TILT * view.slope_sd,
                       kinks=kinks.any_kinks(view.field.contour, radii), corners=sharp)
