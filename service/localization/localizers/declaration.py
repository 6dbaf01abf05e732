"""The checks a declaration of `particles.py` waits on beyond the sweep: the turned check
and its deep pass (`turned.py`), and the certificate of the whole map (`certificate.py`).

Each can only hold a declaration back. The rivals that do are handed to the pool, where
the judge weighs them as modes: explanations the pool had missed. The pool, the sweep's
shares and the judge stay in `particles.py`; this module keeps how far each check has come
and what it found.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from service.localization.localizers.certificate import KEPT, SLACK, Certificate, certify
from service.localization.localizers.convergence import ConvergenceRule, distinct, within
from service.localization.localizers.sweep import Sweep
from service.localization.localizers.turned import (
    DEEP,
    DEEP_RIVALS,
    TURNED,
    TURNED_SLICE,
    TurnedCheck,
    Weighing,
    rivals_clear,
)

AHEAD_MASS = 0.9
"""The leading mode's share from which the checks a declaration waits on are made ahead,
between steps: the turned check and its deep pass to their end, and the certificate. Made
only once the judge would declare, the certificate cost every declaration a step (B2's
median 10 -> 11). Below it the turned check takes a share a step, as a leader whose heading
still moves would start it again."""
CERTIFY_WORK = 100_000
"""Work (`Certificate.work`, boxes judged) a step's background gives the certificate: about
0.1-0.2 s on the project's machine (1.2-1.6 us a box). A larger search goes on over the
next steps, so no update waits on the whole map, at a cost in steps where the map is
large: B3's 80-unit map needs 0.23-1.0 million at its earliest (bumps:80:1, seeds 0-9),
and its median steps went from 11 to 15 (20/20 localized either way)."""
RETRY_READINGS = 4
"""Readings after a certificate that ran out of room before the whole map is searched again
for the same pose (a search that overflows costs up to `certificate.MAX_BOXES` boxes, about
20 steps of background)."""
RENEW = 0.5 * (SLACK + KEPT)
"""A certificate is made anew ahead once its margin falls below this (`Certificate.margin`),
so that the next reading still finds one that stands."""

Add = Callable[[np.ndarray], None]
"""Hands poses to the pool."""
Weights = Callable[[], np.ndarray]
"""Gauss-Newton's weight of every reading, at the pool's current ranges."""


class DeclarationChecks:
    """The turned check, its deep pass and the certificate, for the leader of one pool."""

    def __init__(self, weighing: Weighing, sweep: Sweep, rule: ConvergenceRule,
                 polish_steps: int) -> None:
        self.weighing, self.sweep, self.rule = weighing, sweep, rule
        self.polish_steps = polish_steps
        """Gauss-Newton steps a turned find takes onto the readings."""
        self.reset()

    def reset(self) -> None:
        self.turned = TurnedCheck()
        self.deep = TurnedCheck()
        """The turned check again, polishing `DEEP` cells a share, between steps: it only
        holds a declaration back, and hands the rivals that do to the pool."""
        self.certificate: Certificate | None = None
        """The last complete search of the whole map for rivals of a pose about to be
        declared."""
        self.to_certify: np.ndarray | None = None
        """A pose every other check would declare, whose certificate the next steps make."""
        self.certifying: tuple[Certificate, Iterator[int]] | None = None
        """The search under way, `CERTIFY_WORK` a step, and where it goes on."""

    @property
    def _profile(self) -> bool:
        return self.weighing.surface.map.is_profile

    # -- in the update -----------------------------------------------------------------------
    def clear(self, pose: np.ndarray, history: np.ndarray, add: Add) -> bool:
        """Whether the turned check, its deep pass and the certificate all let `pose` be
        declared, in that order; rivals that hold it back go to `add`."""
        return (self.turned_clear(pose, history) and self.deep_clear(pose, history, add)
                and self.certified(pose, history, add))

    def turned_clear(self, pose: np.ndarray, history: np.ndarray) -> bool:
        """Whether the turned check of `pose`'s heading is complete and its rivals would not
        hold the declaration back (`turned.rivals_clear`); its finds are in the pool
        already."""
        return self._check_clear(self.turned, pose, history, None)

    def deep_clear(self, pose: np.ndarray, history: np.ndarray, add: Add) -> bool:
        """The same for the deep pass, whose rivals go to `add` when they hold it back."""
        return self._check_clear(self.deep, pose, history, add)

    def _check_clear(self, check: TurnedCheck, pose: np.ndarray, history: np.ndarray,
                     add: Add | None) -> bool:
        if not check.covers(float(pose[2]), self.sweep.turned_cells):
            return False
        if rivals_clear(self.weighing, history, pose, check.rivals):
            return True
        if add is not None:
            add(check.rivals)
        return False

    def certified(self, pose: np.ndarray, history: np.ndarray, add: Add) -> bool:
        """Whether a search of the whole map (`certificate.py`) found no pose that would
        hold the declaration of `pose` back. Without a certificate for `pose` one is made
        between steps; the rivals of one that holds it back go to `add`. A search that ran
        out of room (on a knurl's lattice, 100,000 fine boxes survived the bound) holds the
        declaration back, as a rival would. A profile needs none: the
        sweep's cells tile its poses exactly."""
        if self._profile:
            return True
        cert = self.certificate
        if cert is None or not cert.covers(self.weighing, history, pose):
            self.to_certify = pose.copy()
            return False
        if cert.overflowed:
            # the map ruled out too little to be checked whole: nothing is declared on
            # the other checks alone (they passed two poses 26 and 57 mm off on a held-out
            # knurl with one worn patch, seeds 22 and 17, whose truths fitted the readings
            # better). Asked again once `RETRY_READINGS` more readings may rule out more.
            if len(history) >= cert.readings + RETRY_READINGS:
                self.to_certify = pose.copy()
            return False
        if rivals_clear(self.weighing, history, pose, cert.rivals):
            return True
        add(cert.rivals)
        return False

    # -- between steps -----------------------------------------------------------------------
    def between_steps(self, pose: np.ndarray, history: np.ndarray, weights: Weights,
                      mode_mass: float, noisy: bool, add: Add) -> Iterator[int]:
        """The turned check of `pose`'s heading and its deep pass, a share a step, or to
        their end once the leading mode holds `AHEAD_MASS` (a new heading starts them
        again); their finds join the pool. Then the certificate asked for (or, from
        `AHEAD_MASS`, the one the next update may need).

        The turned check ran a share per update, inside it, and held B2's declarations
        back: of 30 episodes (peaks, seeds 0-29), 17 waited 1-4 updates after the rule
        first held, 32 updates in all, for the turned check to complete. Run here, a
        whole check costs milliseconds while the finger moves."""
        heading = float(pose[2])
        self.turned.follow(heading)
        self.deep.follow(heading)
        shares = self.sweep.turned_cells if mode_mass >= AHEAD_MASS else TURNED_SLICE
        cells = min(self.sweep.turned_cells, self.turned.cursor + shares)
        while self.turned.cursor < cells:
            found = self._turned_step(pose, history, weights)
            if len(found):
                add(found)
            yield TURNED
        while self.deep.cursor < cells:
            self._deep_step(pose, history, weights)
            yield DEEP
        if self.to_certify is None and self._may_declare_next(pose, history, mode_mass, noisy):
            self.to_certify = pose.copy()
        if self.to_certify is not None:
            if self.certifying is None or not within(
                    self.certifying[0].pose[np.newaxis], self.to_certify,
                    *self.weighing.same_pose)[0]:  # a search for another pose is moot
                cert = Certificate(pose=self.to_certify, readings=len(history))
                self.certifying = (cert, certify(self.weighing, history, self.to_certify,
                                                 cert))
            self.to_certify = None
        if self.certifying is not None:
            cert, search = self.certifying
            start = cert.work
            for used in search:
                yield used
                if cert.work - start >= CERTIFY_WORK:
                    return  # the rest in the next steps' background
            self.certificate, self.certifying = cert, None

    def _turned_step(self, pose: np.ndarray, history: np.ndarray, weights: Weights
                     ) -> np.ndarray:
        """A share of the turned check: `TURNED_SLICE` cells of `pose` turned and moved
        anywhere, the best `TURNED` polished onto the readings; those that fit nearly as
        well as `pose`, for the pool, and kept as the check's rivals."""
        check = self.turned
        found, _ = check.share(self.weighing, self.sweep, history, weights(), pose, TURNED,
                               self.polish_steps)
        if len(found):
            check.rivals = np.vstack([check.rivals, found])[-TURNED:]
        return found

    def _deep_step(self, pose: np.ndarray, history: np.ndarray, weights: Weights) -> None:
        """A share of the deep turned check: the update's share again, polishing the best
        `DEEP` of its cells; the best distinct finds become its rivals only."""
        found, below = self.deep.share(self.weighing, self.sweep, history, weights(), pose,
                                       DEEP, self.polish_steps)
        found = found[distinct(found, -below, *self.weighing.same_pose)[:DEEP_RIVALS]]
        self.deep.rivals = np.vstack([self.deep.rivals, found])

    def _may_declare_next(self, pose: np.ndarray, history: np.ndarray, mode_mass: float,
                          noisy: bool) -> bool:
        """Whether the next update may declare `pose` (the sweep done, the leading mode
        holding `AHEAD_MASS`) and needs a certificate for it: made now, while the finger
        moves, it is ready when the declaration is; one whose margin fell below `RENEW` is
        made anew."""
        cert = self.certificate
        needed = self.rule.min_readings_noisy if noisy else self.rule.min_readings
        return (not self._profile and self.sweep.checked and mode_mass >= AHEAD_MASS
                and len(history) >= needed  # the next update's readings
                and (cert is None or not cert.covers(self.weighing, history, pose, RENEW)))
