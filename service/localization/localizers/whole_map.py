"""A declaration held until the whole map supports it, for the localizers with no checks
of their own beyond their grid (`grid`, `match`).

Algorithms I-III weigh every cell of their grid, but a cell stands for a range of poses:
on a map with two copies of one terrain (or a half-turned copy), the copy whose cells lay
nearer its exact fit won by the grid's quantization alone, and the other was left out of
the modes the judge weighs. On three such maps of a held-out helper's, `grid` declared the
other copy in 9 runs (93-341 mm away) and `match` in 20 (50-378 mm); `match` also once a
hole's pitch off on a tilted grid of holes (`particles` none in 900 runs). So a declaration
they would make waits for the certificate (`certificate.py`): a search of every pose on
the map for one that fits the readings within `SLACK` nats, and it stands only if none of
those found would hold more than the rule's 1 - mode_mass (`turned.rivals_clear`, the
readings' shared error counted). The search runs in the background between updates
(`Localizer.background`), so no update waits on it and a declaration it allows costs no
move (`base.settle`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from service.localization.localizers.base import Budget
from service.localization.localizers.certificate import Certificate, certify
from service.localization.localizers.convergence import Verdict, within
from service.localization.localizers.turned import Weighing, rivals_clear, slope_weighed

HELD_BACK = "another pose on the map fits the readings as well (the check of the whole map)"
OVERFLOWED = "the map rules out too little to check it whole yet"


class WholeMapCheck:
    """The certificate of one would-be declaration at a time, and what it decided."""

    def __init__(self, weighing: Weighing) -> None:
        self.weighing = weighing
        self._waiting: Verdict | None = None
        """The declaration the search is for, as the judge made it."""
        self._search: Iterator[int] | None = None
        self._certificate: Certificate | None = None

    @property
    def pending(self) -> bool:
        return self._waiting is not None

    def hold(self, verdict: Verdict, history: np.ndarray) -> Verdict:
        """`verdict` as it may be reported now: a declaration is held (not converged) and
        its search begun, unless a finished certificate of the same pose still stands for
        it on `history`; anything else passes unchanged."""
        self._waiting = self._search = None
        if not verdict.converged or verdict.fit is None:
            return verdict
        pose = np.asarray(verdict.fit.pose, dtype=np.float64)
        cert = self._certificate
        if cert is not None and cert.covers(self.weighing, history, pose):
            return self._decided(verdict, history, cert)
        self._certificate = Certificate(pose=pose, readings=len(history))
        self._search = certify(self.weighing, history, pose, self._certificate)
        self._waiting = verdict
        return dataclasses.replace(verdict, converged=False,
                                   held_back="the whole map is being checked")

    def work(self, budget: Budget, history: np.ndarray) -> Verdict | None:
        """Search on within `budget`; the verdict once the search is done, else None."""
        assert self._search is not None and self._waiting is not None
        for _ in self._search:
            if budget.expired():
                return None
        verdict, self._waiting, self._search = self._waiting, None, None
        assert self._certificate is not None
        return self._decided(verdict, history, self._certificate)

    def _decided(self, verdict: Verdict, history: np.ndarray, cert: Certificate) -> Verdict:
        """`verdict` if the certificate clears it; else held back, with the best rival as
        its runner-up and the two weighed on the readings."""
        if cert.overflowed:
            return dataclasses.replace(verdict, converged=False, held_back=OVERFLOWED)
        pose = np.asarray(verdict.fit.pose, dtype=np.float64)
        if rivals_clear(self.weighing, history, pose, cert.rivals):
            return verdict
        rivals = cert.rivals[~within(cert.rivals, pose, *self.weighing.same_pose)]
        ll = slope_weighed(self.weighing, history, np.vstack([[pose], rivals]),
                           self.weighing.fit_sd)
        share = np.exp(ll - ll.max())
        share /= share.sum()
        best = 1 + int(np.argmax(share[1:]))
        return dataclasses.replace(
            verdict, converged=False, held_back=HELD_BACK, mode_mass=float(share[0]),
            runner_up=tuple(float(v) for v in rivals[best - 1]),
            runner_up_mass=float(share[best]))
