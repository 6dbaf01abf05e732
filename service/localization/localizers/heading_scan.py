"""The rotation scan Algorithm II lays its path with: for each position, the heading that
fits the readings best. Grid (position-only) and Match both use it, so it lives apart from
either."""

from __future__ import annotations

import numpy as np

from service.localization.localizers.fitting import offset_residuals
from service.localization.models import rotate
from service.localization.surface import ContactSurface

SCAN = 48
"""Candidate headings per cell in the rotation scan."""


def best_headings(surface: ContactSurface, history: np.ndarray, x: np.ndarray, y: np.ndarray,
                  scan: int = SCAN) -> tuple[np.ndarray, np.ndarray]:
    """For each current position (x, y): the heading laying the path best onto the map,
    and that fit's RMS residual (metres). One (cells x headings x readings) pass."""
    angles = np.arange(scan) * (2 * np.pi / scan)
    d = history[-1]
    dx, dy = rotate(angles[np.newaxis, :], d[0], d[1])
    starts = np.stack([x[:, None] - dx, y[:, None] - dy,
                       np.broadcast_to(angles, (len(x), scan))], axis=-1).reshape(-1, 3)
    r, ok = offset_residuals(surface, starts, history, 0.0)
    rms = np.sqrt(np.mean(np.where(ok, r * r, 1.0), axis=1)).reshape(len(x), scan)
    best = np.argmin(rms, axis=1)
    return angles[best], rms[np.arange(len(x)), best]
