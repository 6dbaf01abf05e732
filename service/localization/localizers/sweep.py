"""The global check: a systematic sweep over every start pose the map allows.

A sampled localizer knows only the hypotheses it holds. When the truth has left its pool,
the posterior over the survivors can look certain and be wrong (a real terrain patch: two
wrong declarations at a leading-mode mass of 0.99999). So no pose is declared until a sweep
has screened the whole pose space against the readings and handed the localizer the
regions that explain them best, to polish and weigh against its leader.

The space is tiled by cells (x, y, heading; position and direction on a profile), each
standing for every pose within it: its centre's residuals are judged with the sd widened
by how far a pose in the cell could move each reading (paper Eq. 4, as the pool's members
are), so the truth's cell scores well wherever the truth is in it. A cell's misfit is the
sum of its readings' z^2, each capped (one slip cannot sink it). Each update screens a
bounded stretch of cells and hands over the best few; the truth's cell ranks among the
first few dozen of a whole sweep even on a few readings (peaks under B2's noise), and the
search for the best abandons a cell as soon as it cannot make the cut, so a cell costs a
reading or two.

The sweep runs in a fixed order that spreads any stretch of it over the whole map, a bounded
number of cells per update, so an update's cost does not grow with the map: a bigger map
takes more updates to cover. A sweep begun once the readings are selective
(`start_readings`) and carried to its end is a check; sweeps repeat with the readings of
their time. The result is a pure function of the readings, the same however it is sliced,
except between cells of equal misfit, which rank by slice (a strict xfail in
tests/service/test_sweep.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from service.localization import kernels
from service.localization.localizers.base import wrap_angle
from service.localization.localizers.convergence import FLOOR
from service.localization.localizers.fitting import (
    STEEP_BLOCK,
    on_pose_space,
    steepest_near,
    typical_slope,
    unanchored,
)
from service.localization.localizers.symmetry import revolution_centre, symmetries
from service.localization.surface import ContactSurface

CAP = 9.0
"""A reading's largest share of a cell's misfit (3 sigmas): one slip cannot fail a cell."""
TURN = 45.0
"""Degrees: `Sweep.turned` screens the headings a multiple of this from a pose's."""
TURNED_CELL = 0.3
"""Step lengths between the positions `Sweep.turned` screens (at most `TURNED_CELLS`)."""
TURNED_CELLS = 32768
SAME_TURN = 2.0
"""Degrees within which two turns are one (`turns_to_check`)."""


@dataclass(frozen=True)
class SweepSettings:
    """How fine and how fast the sweep is; lengths in step lengths."""

    cell: float = 0.6
    """Cell width: a pose in the cell is at most 0.42 steps from its centre."""
    heading_cell_deg: float = 15.0
    cells_per_update: int = 16_384
    start_readings: int = 2
    """Readings (after first contact) before a sweep begins: fewer pass too many cells."""
    readings: int = 8
    """Most readings a cell is screened on."""
    keep: int = 64
    """Cells an update hands over: the best it screened. The truth's cell ranks among the
    first few dozen of a whole sweep on a few readings (peaks, B2), but about 160th of
    38,400 on five readings round a round boss (a mesh's facets: an exact fit every
    11 degrees), where a hand of 32 missed it and a second exact fit was declared."""


class Sweep:
    """Sweeps over every cell of the pose space, a bounded share per update."""

    def __init__(self, surface: ContactSurface, step_length: float, sensor_sigma: float,
                 margin: float, settings: SweepSettings | None = None) -> None:
        self.surface, self.step_length = surface, step_length
        self.settings = s = settings or SweepSettings()
        # without noise a reading still differs from the map by what its samples miss
        self.sensor_sigma = max(sensor_sigma, FLOOR * step_length)
        self.margin = margin
        profile = surface.map.is_profile
        x_max, y_max = surface.map.extent
        width = s.cell * step_length
        nx = max(1, int(np.ceil(x_max / width)))
        ny = 1 if profile else max(1, int(np.ceil(y_max / width)))
        nh = 2 if profile else int(round(360.0 / s.heading_cell_deg))
        self.shape = np.array([nx, ny, nh], dtype=np.int64)
        self.pitch = np.array([x_max / nx, 0.0 if profile else y_max / ny, 2 * np.pi / nh])
        self.origin = np.array([0.0, 0.0, -0.5 * self.pitch[2] if profile else -np.pi])
        self.headings = self.origin[2] + (np.arange(nh) + 0.5) * self.pitch[2]
        self.cells = kernels.sweep_cells(self.shape)
        self.stride = _coprime_stride(kernels.sweep_tiles(self.shape))
        self.reach = (float(np.hypot(*self.pitch[:2])) / 2, float(self.pitch[2]) / 2)
        """How far a pose in a cell can lie from its centre (metres, radians)."""
        self.slopes = steepest_near(surface, 2 * self.reach[0])
        self.slope = typical_slope(surface)
        self.start_reach = self.reach[0]
        """How far (metres) a start handed over can lie from a pose its cell stands for."""
        self.turns = turns_to_check(surface)
        """Radians `turned` turns a heading by."""
        self._turned_grid = self._turned_shape()
        self.turned_cells = kernels.sweep_cells(self._turned_grid[0])
        self.reset()

    def reset(self) -> None:
        self.cursor = 0
        self.begun_at: int | None = None
        """Readings when the current sweep began (None: not begun)."""
        self.bar = np.inf
        """The worst misfit the last update handed over (infinite if it found too few)."""
        self.checked_at: int | None = None
        """Readings when the last sound sweep began: every pose that explains the
        readings since was in a cell it handed over."""

    @property
    def checked(self) -> bool:
        return self.checked_at is not None

    @property
    def remaining(self) -> int:
        """Cells the sweep under way has still to screen (all, before one begins)."""
        return self.cells - self.cursor if self.begun_at is not None else self.cells

    def run(self, history: np.ndarray, take: int | None = None
            ) -> Iterator[tuple[int, np.ndarray]]:
        """One update's share, in slices of about `take` cells (for an anytime job): yields
        the cells screened, and at the end the centres (M, 3) of the `keep` that fit the
        readings best, best first."""
        k = len(history) - 1
        if k < self.settings.start_readings:
            return
        if self.begun_at is None:
            self.begun_at, self.cursor = k, 0
        anchor, use = self._anchor(history)
        # the cells stand for the finger's pose at the anchor reading: the readings round
        # it, relative to it, are the least widened (`spread`)
        offset = history[anchor, :3].copy()
        history = np.vstack([history[anchor], history[use]])
        history[:, :3] -= offset
        spread = self.reach[0] + np.hypot(history[:, 0], history[:, 1]) * self.reach[1]
        k = len(use)
        # a cell must also beat (nearly) the worst handed over last time: most cells then
        # fail on their first reading or two
        limit = min(k + 3.0 * np.sqrt(2.0 * k) + CAP, 1.2 * self.bar)
        left = self.settings.cells_per_update
        poses, misfit = np.empty((0, 3)), np.empty(0)
        while left > 0 and self.cursor < self.cells:
            count = min(left, take or left, self.cells - self.cursor)
            p, m = kernels.sweep_screen(
                self.surface.centre_heights, self.slopes,
                STEEP_BLOCK * self.surface.map.spacing, self.surface.map.spacing,
                self.surface.map.extent, self.surface.map.is_profile, self.cursor, count,
                self.stride, self.shape, self.origin, self.pitch, self.headings, history,
                self.sensor_sigma, spread, self.margin, CAP, limit, self.settings.keep)
            poses, misfit = np.vstack([poses, p]), np.concatenate([misfit, m])
            self.cursor += count
            left -= count
            if self.cursor >= self.cells:  # a whole sweep
                self.checked_at, self.begun_at = self.begun_at, None
            yield count, np.empty((0, 3))
        best = np.argsort(misfit, kind="stable")[:self.settings.keep]
        self.bar = float(misfit[best[-1]]) if len(best) == self.settings.keep else np.inf
        yield 0, self._starts(poses[best], offset)

    def turned(self, history: np.ndarray, heading: float, first: int, count: int, best: int
               ) -> np.ndarray:
        """Of turned cells `first` .. `first + count` (of `turned_cells`), the start poses
        of the `best` that fit the readings best, best first: every position on the map, at
        `heading` turned by each of `turns`. Where a part repeats a feature turned (a square
        pocket, four alike holes, a knurl's lattice), such a pose reads what a pose at
        `heading` reads.

        A screen over positions only, `TURNED_CELL` steps apart (further on a map too large
        for `TURNED_CELLS` of them), at exact headings: no cell stands for a range of
        headings, so readings far from the start are not blurred by one, as the sweep's
        are, and every reading counts."""
        shape, pitch = self._turned_grid
        spread = np.full(len(history), float(np.hypot(*pitch[:2])) / 2)
        poses, _ = kernels.sweep_screen(
            self.surface.centre_heights, self.slopes, STEEP_BLOCK * self.surface.map.spacing,
            self.surface.map.spacing, self.surface.map.extent, self.surface.map.is_profile,
            first, min(count, self.turned_cells - first), 1, shape, np.zeros(3), pitch,
            self._turned_headings(heading), history, self.sensor_sigma, spread, self.margin, CAP,
            np.inf, best)
        return on_pose_space(self.surface, poses)

    def _turned_headings(self, heading: float) -> np.ndarray:
        """`heading` turned by each of `turns`; the multiples of `TURN` (or a profile's half
        turn) reckoned as a grid of headings a `TURN` apart, from the first, as they were
        before the surface's own turns joined them, so the same sums give the same bits."""
        pitch = np.deg2rad(TURN)
        first = np.pi if self.surface.map.is_profile else pitch
        grid = (heading + first - 0.5 * pitch) + (np.arange(len(self.turns)) + 0.5) * pitch
        index = np.round((self.turns - first) / pitch)
        regular = np.abs(self.turns - (first + index * pitch)) < 1e-12
        return np.where(regular, grid[np.clip(index, 0, len(grid) - 1).astype(np.int64)],
                        heading + self.turns)

    def _turned_shape(self) -> tuple[np.ndarray, np.ndarray]:
        """The grid `turned` screens: positions (x, y) and turns, and their pitch."""
        profile = self.surface.map.is_profile
        x_max, y_max = self.surface.map.extent
        area = x_max * (1.0 if profile else y_max) * len(self.turns)
        # coarser on a large map: the work is bounded, as every update's is
        width = max(TURNED_CELL * self.step_length,
                    area / TURNED_CELLS if profile else np.sqrt(area / TURNED_CELLS))
        shape = np.array([max(1, int(np.ceil(x_max / width))),
                          1 if profile else max(1, int(np.ceil(y_max / width))),
                          len(self.turns)], dtype=np.int64)
        return shape, np.array([x_max / shape[0], 0.0 if profile else y_max / shape[1], 0.0])

    def _anchor(self, history: np.ndarray) -> tuple[int, np.ndarray]:
        """The reading to judge cells from, and the `readings` others nearest it.

        Readings far from the anchor are widened by the cell's heading range times their
        distance, so only those round it tell cells apart; of all the readings, the anchor
        is the one whose neighbours differ most in height for that widening. Anchored at
        the start, a walk that began on a plain judged cells on flat readings alone, which
        thousands of cells fit: on a plate the truth's cell never made the hand in 40
        steps, and its half-turn image was declared."""
        xy = history[:, :2]
        distance = np.hypot(*(xy[:, np.newaxis, :] - xy[np.newaxis, :, :]).transpose(2, 0, 1))
        np.fill_diagonal(distance, np.inf)
        count = min(self.settings.readings, len(history) - 1)
        near = np.argsort(distance, axis=1, kind="stable")[:, :count]
        rise = history[near, 2] - history[:, 2:3]
        spread = self.reach[0] + np.take_along_axis(distance, near, axis=1) * self.reach[1]
        told = np.sum(rise**2 / (self.sensor_sigma**2 + (self.slope * spread) ** 2), axis=1)
        anchor = int(np.argmax(told))
        if told[anchor] < 2.0 * told[0]:
            anchor = 0
        return anchor, near[anchor]

    def _starts(self, anchored: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Start poses of cells anchored at a reading `offset` (x, y in the start's frame)
        from the start, those on the map."""
        self.start_reach = self.reach[0] + float(np.hypot(*offset[:2])) * self.reach[1]
        starts = unanchored(anchored, offset)
        x_max, y_max = self.surface.map.extent
        inside = (starts[:, 0] >= 0) & (starts[:, 0] <= x_max)
        if not self.surface.map.is_profile:
            inside &= (starts[:, 1] >= 0) & (starts[:, 1] <= y_max)
        return on_pose_space(self.surface, starts[inside])


def turns_to_check(surface: ContactSurface) -> np.ndarray:
    """The turns (radians) under which a part may repeat a feature: every multiple of `TURN`
    degrees (a half turn on a profile), and the turns other than quarter turns the surface
    nearly repeats under as a whole (`symmetry.symmetries`: a hexagonal lattice's 60
    degrees, a gear's teeth). A knurl declared 60 degrees off: that turn was in no list the
    check screened, and the images of single motions missed the lattice shift that the
    truth lay at; the screen moves the turned pose anywhere. A surface of revolution
    repeats under every turn, each about its axis alone: its images stand for them all
    (`symmetry.revolution_centre`)."""
    if surface.map.is_profile:
        return np.array([np.pi])
    turns = list(np.deg2rad(np.arange(TURN, 360.0 - 1e-9, TURN)))
    motions = symmetries(surface)
    if revolution_centre(motions, surface.map.extent) is not None:
        return np.array(turns)
    for k in np.unique(np.round(motions[:, 0] * 90.0, 1)):
        if k % 90.0 and np.all(np.abs(wrap_angle(np.deg2rad(k) - np.array(turns)))
                               > np.deg2rad(SAME_TURN)):
            turns.append(float(np.deg2rad(k)))
    return np.array(sorted(turns))


def _coprime_stride(n: int) -> int:
    """A stride near n / golden ratio sharing no factor with n: stepping by it visits every
    tile once, and consecutive tiles lie far apart."""
    stride = max(1, int(n / 1.6180339887))
    while np.gcd(stride, n) != 1:
        stride += 1
    return stride
