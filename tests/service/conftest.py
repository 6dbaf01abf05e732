"""Surfaces a helper wrote from scratch for a held-out check (200 x 200 mm at 1 mm, heights
in metres), kept where a wrong declaration was found on them: fixtures give each as a
`.npy` map file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

_X, _Y = np.meshgrid(np.arange(201) * 0.001, np.arange(201) * 0.001)


@pytest.fixture()
def texture_map(tmp_path: Path) -> Path:
    """`texture_with_a_bowl_and_a_bump` as a map file."""
    path = tmp_path / "texture.npy"
    np.save(path, texture_with_a_bowl_and_a_bump())
    return path


@pytest.fixture()
def plate_map(tmp_path: Path) -> Path:
    """`machined_plate` as a map file."""
    path = tmp_path / "plate.npy"
    np.save(path, machined_plate())
    return path


def texture_with_a_bowl_and_a_bump() -> np.ndarray:
    """A 30 mm egg-crate texture, 3 mm peak to peak, on a bowl 0.6 mm deep, with one 0.3 mm
    bump: the bowl and the bump are all that tell its near-symmetric poses apart, about the
    size of B2's mismatch."""
    z = 0.0015 * np.sin(2 * np.pi * _X / 0.030) * np.sin(2 * np.pi * _Y / 0.030)
    z += 0.0006 * ((_X - 0.1) ** 2 + (_Y - 0.1) ** 2) / 0.1**2
    mark = (0.1269840715151213384, 0.1442143955870480720)
    return z + 0.0003 * np.exp(-((_X - mark[0]) ** 2 + (_Y - mark[1]) ** 2) / (2 * 0.0025**2))


def machined_plate() -> np.ndarray:
    """A flat plate with a 4 mm pocket (2 mm floor fillets), two 3 mm bosses (1.5 mm
    fillets at their feet) and an oblique 2.5 mm slot."""
    z = _pocket(0.070, 0.125, 0.070, 0.045, 0.006, 0.004, 0.002)
    for cx, cy, r in ((0.150, 0.150, 0.009), (0.140, 0.055, 0.007)):
        rr = np.hypot(_X - cx, _Y - cy)
        fillet = 0.0015
        boss = np.where(rr <= r, 0.003, 0.0)
        ring = (rr > r) & (rr < r + fillet)
        t = rr[ring] - r
        boss[ring] = fillet - np.sqrt(np.maximum(fillet**2 - (fillet - t) ** 2, 0))
        z = np.where(rr < r + fillet, np.maximum(z, boss), z)
    centre, angle = np.array([0.060, 0.050]), np.deg2rad(30)
    u = np.array([np.cos(angle), np.sin(angle)])
    px, py = _X - centre[0], _Y - centre[1]
    along = np.clip(px * u[0] + py * u[1], -0.0225, 0.0225)
    return np.where(np.hypot(px - along * u[0], py - along * u[1]) < 0.003,
                    np.minimum(z, -0.0025), z)


def _pocket(cx: float, cy: float, w: float, h: float, corner: float, depth: float,
            fillet: float) -> np.ndarray:
    dx, dy = np.abs(_X - cx) - (w / 2 - corner), np.abs(_Y - cy) - (h / 2 - corner)
    inward = -(np.hypot(np.maximum(dx, 0), np.maximum(dy, 0))
               + np.minimum(np.maximum(dx, dy), 0) - corner)
    t = np.clip(fillet - inward, 0, fillet)
    rise = fillet - np.sqrt(np.maximum(fillet**2 - t**2, 0))
    return np.where(inward > 0, -depth + rise, 0.0)
