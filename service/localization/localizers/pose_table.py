"""The discrete start-pose table of Algorithm III (paper §3.3): grid positions x headings."""

from __future__ import annotations

import numpy as np

from service.errors import ConfigError
from service.localization.surface import HeightMap


def grid_positions(height_map: HeightMap, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions k * pitch for k = 1 .. floor(extent / pitch) - 2 along each axis.

    On the paper's 20-unit map with a 1-unit pitch this is 1..18, its 324 locations.
    """
    if not pitch > 0:
        raise ConfigError(f"pose-table pitch must be > 0 metres, got {pitch}")
    x_max, y_max = height_map.extent
    xs = pitch * np.arange(1, int(np.floor(x_max / pitch + 1e-9)) - 1)
    ys = np.zeros(1) if height_map.is_profile else (
        pitch * np.arange(1, int(np.floor(y_max / pitch + 1e-9)) - 1))
    if xs.size == 0 or ys.size == 0:
        raise ConfigError(
            f"the map ({x_max:.4g} x {y_max:.4g} m) is too small for a pose table with pitch "
            f"{pitch:.4g} m; use a smaller step or a larger map")
    return xs, ys


def pose_table(height_map: HeightMap, pitch: float, headings: int) -> np.ndarray:
    """All (x, y, heading) entries, shape (N, 3); profiles get headings 0 and pi only."""
    if headings < 1:
        raise ConfigError(f"pose table needs at least one heading, got {headings}")
    xs, ys = grid_positions(height_map, pitch)
    angles = (np.array([0.0, np.pi]) if height_map.is_profile
              else np.arange(headings) * (2 * np.pi / headings))
    y, x, a = np.meshgrid(ys, xs, angles, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), a.ravel()])
