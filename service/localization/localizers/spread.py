"""Spread of a set of pose hypotheses: positional and circular heading standard deviation."""

from __future__ import annotations

import numpy as np


def pose_spread(poses: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, float]:
    """(position sd in metres, heading sd in radians) of weighted poses (N, 3)."""
    if len(poses) == 0:
        return float("nan"), float("nan")
    w = np.full(len(poses), 1.0 / len(poses)) if weights is None else weights / weights.sum()
    mean_xy = w @ poses[:, :2]
    pos_var = w @ np.sum((poses[:, :2] - mean_xy) ** 2, axis=1)
    resultant = min(abs(w @ np.exp(1j * poses[:, 2])), 1.0)  # rounding can exceed 1
    heading_sd = abs(float(np.sqrt(-2 * np.log(max(resultant, 1e-300)))))
    return float(np.sqrt(pos_var)), heading_sd
