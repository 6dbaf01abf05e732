"""The global sweep (`sweep.py`): slicing never changes what it hands over."""

from __future__ import annotations

import numpy as np
import pytest

from service.localization.localizers.fitting import sample
from service.localization.localizers.sweep import SAME_TURN, Sweep, SweepSettings, turns_to_check
from service.localization.maps import load_map
from service.localization.surface import HeightMap, contact_surface

STEP = 0.01
PATH = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [1.0, -1.0], [0.0, -1.0],
                 [0.0, -2.0], [-1.0, -2.0], [-1.0, -3.0]]) * STEP


def _readings(surface, start: np.ndarray) -> np.ndarray:
    """Noise-free readings (K, 3) of a finger that starts at `start` and walks PATH."""
    c, s = np.cos(start[2]), np.sin(start[2])
    x = start[0] + c * PATH[:, 0] - s * PATH[:, 1]
    y = start[1] + s * PATH[:, 0] + c * PATH[:, 1]
    z = sample(surface, x, y)[0]
    return np.column_stack([PATH, z - z[0]])


def _hand_over(sweep: Sweep, history: np.ndarray, take: int | None) -> np.ndarray:
    """The starts one update of `sweep` hands over."""
    starts = [s for _, s in sweep.run(history, take) if len(s)]
    return starts[-1] if starts else np.empty((0, 3))


@pytest.fixture(scope="module")
def pattern():
    return contact_surface(load_map("pattern:20:7"), 0.008)


@pytest.mark.xfail(strict=True, reason="not fixed: equal misfits rank by slice (below)")
@pytest.mark.parametrize("take", [777, 4096])
def test_slicing_never_changes_what_a_sweep_hands_over(pattern, take):
    """`sweep.py` promises the same hand-over however an update is sliced, so that the
    daemon's budgeted updates match `haptic run`'s whole ones. A noise-free walk on a plain
    gives many cells the same misfit, and then it does not: within a slice the later of
    two equal cells wins, across slices the earlier. Ranking by (misfit, place in the
    sweep) fixes it, but changes which cells are handed over in noisy runs too, and on
    `haptic bench objects --map-seeds 0,...,8` it moved the wrong declarations (3 to 6 in
    720 runs, see test_localizers_convergence), so it waits for the hand-over's fix."""
    history = _readings(pattern, np.array([0.05, 0.15, -2.0]))
    whole, sliced = (Sweep(pattern, STEP, 0.0002, 0.0005, SweepSettings(cells_per_update=9000))
                     for _ in range(2))
    for _ in range(3):  # three updates: the bar each leaves carries into the next
        a, b = _hand_over(whole, history, None), _hand_over(sliced, history, take)
        assert np.array_equal(a, b)
        assert whole.bar == sliced.bar and whole.cursor == sliced.cursor


def test_a_pose_turned_about_a_square_pocket_is_found_anywhere():
    """A square pocket reads the same turned a quarter about its centre: `Sweep.turned`
    finds that pose, though no symmetry of the whole plate relates the two (a boss off to
    one side breaks it)."""
    axis = np.arange(0.0, 0.2001, 0.001)
    x, y = np.meshgrid(axis, axis)
    heights = np.where((np.abs(x - 0.07) <= 0.015) & (np.abs(y - 0.07) <= 0.015), -0.005, 0.0)
    heights = heights + np.where(np.hypot(x - 0.15, y - 0.15) <= 0.01, 0.005, 0.0)
    surface = contact_surface(HeightMap(heights, 0.001), 0.008)
    assert _turned_check_finds(surface, np.array([0.062, 0.066, 0.3]),
                               np.array([0.07, 0.07]), np.pi / 2, best=64, heading_tol=1e-9)


def test_a_pose_turned_by_a_lattices_own_turn_is_found_anywhere(hex_map):
    """A hexagonal lattice of bumps reads the same turned by 60 degrees about any bump, a turn
    no multiple of 45 degrees comes near: the surface's own turns are screened too
    (`turns_to_check`), so the turned check finds that pose wherever it lies (the lattice's
    own bumps differ by up to 0.12 mm under it, a sampled map's smoothing)."""
    surface = contact_surface(load_map(str(hex_map), 0.001), 0.008)
    assert np.any(np.abs(np.rad2deg(turns_to_check(surface)) - 60.0) < SAME_TURN)
    # about a bump of the lattice; a lattice has hundreds of poses that read alike: all
    # that fit are kept here
    assert _turned_check_finds(surface, np.array([0.0877, 0.081, 1.29]),
                               np.array([0.1, 0.1]), np.pi / 3, best=8192,
                               heading_tol=np.deg2rad(SAME_TURN))


def _turned_check_finds(surface, start: np.ndarray, centre: np.ndarray, angle: float, *,
                        best: int, heading_tol: float) -> bool:
    """Whether `Sweep.turned`, over all its cells (keeping the `best` of each slice), hands
    over the pose `start` turned by `angle` about `centre`, from the readings of PATH."""
    c, s = np.cos(angle), np.sin(angle)
    expected = np.append(centre + np.array([[c, -s], [s, c]]) @ (start[:2] - centre),
                         start[2] + angle)
    sweep = Sweep(surface, STEP, 0.0002, 0.0005)
    readings = _readings(surface, start)
    found = np.vstack([sweep.turned(readings, start[2], first, 8192, best)
                       for first in range(0, sweep.turned_cells, 8192)])
    gap = np.hypot(found[:, 0] - expected[0], found[:, 1] - expected[1])
    turned = np.abs(np.angle(np.exp(1j * (found[:, 2] - expected[2]))))
    return bool(np.any((gap <= 0.3 * STEP) & (turned <= heading_tol)))


def test_a_surface_without_turns_of_its_own_is_checked_at_multiples_of_45_degrees(pattern):
    assert np.allclose(np.rad2deg(turns_to_check(pattern)), np.arange(45.0, 360.0, 45.0))
