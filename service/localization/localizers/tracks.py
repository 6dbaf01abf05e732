"""Mode tracks: the distinct poses that explain the readings, kept until evidence kills them.

A bounded pool can lose a mode for want of room or to sampling drift; on a periodic surface
that would leave one of many equally good modes alone and declared. So a sampled localizer
also keeps a small set of *tracks*: mode centres taken from its pool while they are
plausible, each polished onto every reading at every update and judged at the sensor's own
sd. A track is dropped only when it fits clearly worse than the best one (or merges with a
better track), never for capacity. The probability of the leading mode is its share among
the tracks.
"""

from __future__ import annotations

import numpy as np

from service.localization.localizers.convergence import distinct
from service.localization.localizers.fitting import fit_log_likelihood, gauss_newton
from service.localization.surface import ContactSurface


class ModeTracks:
    """Up to `limit` polished mode centres and their log likelihoods."""

    def __init__(self, limit: int = 64, drop: float = 30.0) -> None:
        self.limit = limit
        self.drop = drop
        self.centres = np.empty((0, 3))
        self.ll = np.empty(0)

    def update(self, surface: ContactSurface, history: np.ndarray, candidates: np.ndarray,
               *, sd: float, position_tol: float, heading_tol: float, margin: float,
               outlier_probability: float, outlier_range: float) -> None:
        """Add `candidates` (best first), polish all, keep the best of each neighbourhood
        and drop the losers. A candidate near a track joins too: if it fits better it is
        the mode there (on fine terrain two modes lie a few millimetres apart)."""
        if len(candidates):
            self.centres = np.vstack([self.centres, candidates[:self.limit]])
        if len(self.centres) == 0:
            self.ll = np.empty(0)
            return
        self.centres = gauss_newton(surface, self.centres, history, np.ones(len(history)),
                                    iterations=2, max_move=position_tol)
        ll = fit_log_likelihood(surface, self.centres, history, sd, margin,
                                outlier_probability, outlier_range)
        keep = distinct(self.centres, ll, position_tol, heading_tol)
        keep = keep[ll[keep] >= ll[keep[0]] - self.drop][:self.limit]
        self.centres, self.ll = self.centres[keep], ll[keep]

    def shares(self) -> np.ndarray:
        """Probability of each track (best first), from the likelihoods."""
        if len(self.ll) == 0:
            return self.ll
        w = np.exp(self.ll - self.ll[0])
        return w / w.sum()
