"""The turned checks of `particles.py`: rivals the global sweep may pass over.

A part that repeats a feature turned (a square pocket, four alike holes, a knurl's lattice)
reads under the leading pose turned and moved as under the pose itself. The sweep ranks
coarse cells that each stand for 15 degrees of heading, and near any feature hundreds of
them fit almost exactly: which of them it hands over decided whether a part's turned
feature was ever tried. On map seeds no benchmark used, 9 of 11 wrong declarations in
1,440 runs were a 90-180 degree turn off (pattern:20:7, seed 1, 21 mm off: the truth's fit
was the better) while the truth, a turn of the declared pose about a feature, never joined
the pool. So a turned check screens the leader turned by each of the surface's turns
(`Sweep.turned`) and moved anywhere, a share of the cells at a time, polishes the best onto
the readings, and holds a declaration back while any find fits comparably.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.localization.localizers.base import wrap_angle
from service.localization.localizers.convergence import shared_error_mass, within
from service.localization.localizers.fitting import (
    fit_log_likelihood,
    gauss_newton,
    offset_residuals,
)
from service.localization.localizers.refine import reading_sigmas, reading_sigmas_each
from service.localization.localizers.sweep import Sweep
from service.localization.surface import ContactSurface

TURNED_SLICE = 8192
"""Turned cells (`Sweep.turned`) a share of a turned check screens."""
TURNED = 128
"""Of those, the best that the turned check polishes (and the rivals it keeps)."""
DEEP = 1024
"""Of a share's cells, those the deep turned check polishes between steps. The screen's
misfit is a bound that forgives readings near steep ground, so on a part with pockets it
ranks coarsely: on plate:20:40 (seed 11, 15 readings) the truth's cells ranked 1,272nd
and 1,842nd of 31,423, and a half turn was declared 113 mm off."""
DEEP_RIVALS = 32
"""Most distinct finds of a deep share kept as the deep check's rivals."""
TRIAL_STEPS = 2
"""Gauss-Newton steps every screened cell takes before the loose cut (`LOOSE`)."""
TURNED_DRIFT = np.deg2rad(5.0)
"""Radians the leader's heading may move before its turned check starts again."""
LOOSE = 50.0
"""Nats below the declared pose, at one sd for every reading, within which a turned pose
is polished to the end and weighed again reading by reading (`slope_weighed`)."""


@dataclass(frozen=True)
class Weighing:
    """How a turned check weighs poses against the readings: the localizer's own settings."""

    surface: ContactSurface
    sigma: float
    """The sensor's sd (metres); at 1 um or less the readings are noise-free."""
    fit_sd: float
    """Reading sd at which polished poses are compared."""
    position_sigma: float
    margin: float
    outlier_probability: float
    outlier_range: float
    step_length: float
    same_pose: tuple[float, float]
    """Position and heading within which two poses are one."""
    mode_mass: float
    """The share the declared pose must hold (`ConvergenceRule.mode_mass`)."""

    @property
    def noisy(self) -> bool:
        return self.sigma > 1e-6


@dataclass
class TurnedCheck:
    """How far a turned check of the leader's heading has come: the heading it checks, the
    turned cells screened and the rivals found."""

    heading: float | None = None
    cursor: int = 0
    rivals: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))

    def follow(self, heading: float) -> None:
        """Start again for `heading` if it moved more than `TURNED_DRIFT` from the one
        checked."""
        if self.heading is None or abs(wrap_angle(heading - self.heading)) > TURNED_DRIFT:
            self.heading, self.cursor = heading, 0
            self.rivals = np.empty((0, 3))

    def covers(self, heading: float, cells: int) -> bool:
        """Whether the check is complete for `heading` (within `TURNED_DRIFT`)."""
        return (self.heading is not None and self.cursor >= cells
                and abs(wrap_angle(heading - self.heading)) <= TURNED_DRIFT)

    def share(self, weighing: Weighing, sweep: Sweep, history: np.ndarray,
              weights: np.ndarray, pose: np.ndarray, keep: int, steps: int
              ) -> tuple[np.ndarray, np.ndarray]:
        """The next share: its turned cells' best `keep` polished onto the readings (each
        weighed by `weights`, Gauss-Newton's), in `TRIAL_STEPS` and then, those still within
        `LOOSE` of `pose`, to `steps` in all; those still within it, not `pose` itself, and
        how far below it each scores (nats)."""
        surface = weighing.surface

        def polished(poses: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
            """Poses a few more steps on, and how far below `pose` each then scores."""
            poses = gauss_newton(surface, poses, history, weights, iterations=iterations,
                                 max_move=sweep.start_reach)
            ll = fit_log_likelihood(surface, np.vstack([[pose], poses]), history,
                                    weighing.fit_sd, weighing.margin,
                                    weighing.outlier_probability, weighing.outlier_range)
            return poses, ll[0] - ll[1:]

        assert self.heading is not None
        screened = sweep.turned(history, self.heading, self.cursor, TURNED_SLICE, keep)
        self.cursor += TURNED_SLICE
        # every screened cell a couple of steps on; every one that may still fit the rest of
        # the way: on a lattice dozens fit alike, and the best 16 of them once left the
        # truth out (a knurl declared a half turn off)
        found, below = polished(screened, TRIAL_STEPS)
        found, below = found[below <= LOOSE], below[below <= LOOSE]
        if len(found):
            found, below = polished(found, steps - TRIAL_STEPS)
        kept = (below <= LOOSE) & ~within(found, pose, *weighing.same_pose)
        return found[kept], below[kept]


def rivals_clear(weighing: Weighing, history: np.ndarray, pose: np.ndarray,
                 rivals: np.ndarray) -> bool:
    """Whether none of `rivals` would hold more than the rule's 1 - mode_mass of the
    probability against `pose`, each reading weighed as the refinement weighs it."""
    rivals = rivals[~within(rivals, pose, *weighing.same_pose)]
    if len(rivals) == 0:
        return True
    # at one sd for all, a wall's readings made the truth 17 nats worse than a quarter
    # turn whose fit was in fact poorer (plate:20:5, seed 5)
    poses = np.vstack([[pose], rivals])
    ll = slope_weighed(weighing, history, poses, weighing.fit_sd)
    share = weighing.mode_mass
    if np.any(ll[1:] >= ll[0] + np.log((1.0 - share) / share)):
        return False
    if not weighing.noisy:
        return True
    # and with the readings' shared error counted, as the judge weighs its own rivals:
    # weighed as independent, 35 readings on a worn 12 mm knurl put the truth, a half
    # turn away, 7.4 nats below the leader, and the leader was declared; counted as
    # shared, the leader held 56 % (a held-out surface, seed 38)
    sds = reading_sigmas(weighing.surface, history, pose, max(weighing.sigma, 1e-9),
                         weighing.position_sigma)
    return shared_error_mass(weighing.surface, history, poses, sds, weighing.sigma,
                             weighing.step_length, weighing.margin,
                             *weighing.same_pose) >= share


def slope_weighed(weighing: Weighing, history: np.ndarray, poses: np.ndarray, sd: float
                  ) -> np.ndarray:
    """Gaussian log likelihood of every reading for each pose, the height offset fitted,
    each reading's sd `sd` widened by the position noise times the slope under it."""
    r, ok = offset_residuals(weighing.surface, poses, history, weighing.margin)
    sds = reading_sigmas_each(weighing.surface, history, poses, sd, weighing.position_sigma)
    ll = -0.5 * np.sum((r / sds) ** 2, axis=1) - np.sum(np.log(sds), axis=1)
    return np.where(ok.all(axis=1), ll, -np.inf)
