"""Images of the leader that polishing left far behind it, searched for on the map's grid.

A symmetry is found on the map's grid, so the image it makes of the leader may lie a sample
or two off the pose it stands for, and beside sharp walls Gauss-Newton does not cross that.
On a held-out plate of 16 holes, one larger, the truth was an image of a leader 107 mm
away and fitted as well as it, but the image lay 2.6 mm off, polished to 3,000 nats worse,
and the leader was given 100 %. The judge (`convergence.judge`) searches a few samples
around such images when the leader leads alone, and only then.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.localization.localizers.fitting import gauss_newton
from service.localization.surface import ContactSurface

IMAGE_SEARCH_SAMPLES = 2
"""Map samples each way an image of the leader is searched over (then polished, a sample
further at most): the held-out plate's image lay 2.6 samples off."""
IMAGE_SEARCH_POSES = 500
"""Most poses the search tries in one judgement: the worst-fitting images go without."""
WORSE_BY = 10.0
"""Nats by which an image must fit worse than the leader to be searched around; and by
which the leader must lead every mode for the search to run at all (`leads_alone`): only
then would the images' misfit give it a share it may not have."""


def leads_alone(ll: np.ndarray, images_ll: np.ndarray) -> bool:
    """Whether the leader fits `WORSE_BY` better than every other mode and image: then its
    share rests on the images fitting as badly as they do."""
    rest = np.sort(np.concatenate([ll, images_ll]))[::-1]
    return len(rest) > 1 and rest[0] - rest[1] >= WORSE_BY


def images_searched(surface: ContactSurface, history: np.ndarray, images_: np.ndarray,
                    ll: np.ndarray, best: float, score: Callable[[np.ndarray], np.ndarray]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The images and their log likelihoods (`score`), each moved to its best fit within
    `IMAGE_SEARCH_SAMPLES` map samples (then polished) where polishing left it `WORSE_BY`
    nats behind the leader's `best`, the best fitting first, at most `IMAGE_SEARCH_POSES`
    poses in all; and those it moved to within `WORSE_BY` of the leader (found)."""
    behind = np.flatnonzero(ll < best - WORSE_BY)
    if len(behind) == 0:
        return images_, ll, np.empty((0, 3))
    k = np.arange(-IMAGE_SEARCH_SAMPLES, IMAGE_SEARCH_SAMPLES + 1) * surface.map.spacing
    dx, dy = (a.ravel() for a in np.meshgrid(k, k))
    per = len(dx)
    behind = behind[np.argsort(-ll[behind], kind="stable")][:max(IMAGE_SEARCH_POSES // per, 1)]
    tried = np.repeat(images_[behind], per, axis=0)
    tried[:, 0] += np.tile(dx, len(behind))
    tried[:, 1] += np.tile(dy, len(behind))
    pick = np.argmax(score(tried).reshape(len(behind), per), axis=1)
    moved = tried.reshape(len(behind), per, 3)[np.arange(len(behind)), pick]
    moved = gauss_newton(surface, moved, history, np.ones(len(history)), iterations=3,
                         max_move=surface.map.spacing)
    again = score(moved)
    better = again > ll[behind]
    images_, ll = images_.copy(), ll.copy()
    images_[behind[better]], ll[behind[better]] = moved[better], again[better]
    found = np.zeros(len(ll), dtype=bool)
    found[behind[better & (again >= best - WORSE_BY)]] = True
    return images_, ll, images_[found]
