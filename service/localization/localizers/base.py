"""The localizer contract: every algorithm holds hypotheses its own way behind this.

Updates are anytime (ARCHITECTURE.md "Bounded work"): `begin_update` hands over a
measurement, `work(budget)` does a bounded slice and says whether the update is complete,
so a real-time loop can spread one update over several ticks. `update` runs one to the end.
`background(budget)` is work between updates that only a declaration waits on (a global
check): a fixed share per step, run while the finger moves, so it delays neither the next
move nor, however long a move takes, changes any result. Its finds count from the next
update on.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np

from service.localization.models import MotionModel, SensorModel
from service.localization.surface import ContactSurface


@dataclass(frozen=True)
class Measurement:
    """The finger's centre relative to its first contact, in its own frame (metres)."""

    step: int
    displacement: np.ndarray
    """(dx, dy, dz) since the first contact."""
    blocked: bool = False
    t_ns: int = 0
    command: tuple[float, float] = (0.0, 0.0)
    """The step commanded (dx, dy) in the finger's frame: with `blocked`, where the finger
    could not go."""


READING_COLUMNS = 5
"""A reading as localizers keep it: (dx, dy, dz) since first contact, then the blocked
step's command (wx, wy) when the map's edge stopped it, else zeros."""


def reading_row(m: Measurement, walls: bool) -> np.ndarray:
    """`m` as a history row. A blocked step is evidence only where the map's edge is what
    blocks (`walls`, the simulated world): its command then says the target lay off the
    map. On hardware a joint limit also stops a step, and the row carries no such claim."""
    row = np.zeros(READING_COLUMNS)
    row[:3] = np.asarray(m.displacement, dtype=np.float64)[:3]
    if walls and m.blocked:
        row[3:] = m.command
    return row


@dataclass(frozen=True)
class Budget:
    """How much one `work` call may do: a monotonic deadline and/or a count of hypotheses."""

    deadline_ns: int | None = None
    max_items: int | None = None
    """At most this many hypotheses processed in the call (at least one slice is done)."""

    def __post_init__(self) -> None:
        if self.max_items is not None and self.max_items < 1:
            raise ValueError(f"a budget's max_items must be >= 1, got {self.max_items}")

    @classmethod
    def unlimited(cls) -> Budget:
        return cls()

    @classmethod
    def seconds(cls, s: float) -> Budget:
        return cls(deadline_ns=time.monotonic_ns() + int(s * 1e9))

    def expired(self) -> bool:
        return self.deadline_ns is not None and time.monotonic_ns() >= self.deadline_ns

    def fits(self, duration_ns: int) -> bool:
        """Whether work expected to take `duration_ns` would still end by the deadline."""
        return self.deadline_ns is None or time.monotonic_ns() + duration_ns <= self.deadline_ns


@dataclass(frozen=True)
class Estimate:
    """What a localizer believes now, and how sure it is."""

    pose: tuple[float, float, float] | None
    """Best (x0, y0, heading) of the start pose in the map frame, or None with no candidates."""
    candidates: int
    converged: bool
    position_sd: float = float("nan")
    heading_sd: float = float("nan")
    mode_mass: float = float("nan")
    """The leading mode's share of the weight given the modes: a ranking, over-confident as
    a chance where the readings share the map's error (BENCHMARKS.md, sixteenth session)."""
    runner_up: tuple[float, float, float] | None = None
    runner_up_mass: float = 0.0
    information: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(3, 3) what the readings tell about (x0, y0, heading) at `pose`, where the
    localizer has fitted it (`refine.Fit.information`): which way the pose is still loose."""
    pending: bool = False
    """Only the background's checks stand between `pose` and a declaration: run
    `background` before the next move, and the estimate may then be converged (`settle`)."""
    held_back: str = ""
    """Not converged: the first condition that held the declaration back, in words ("" when
    the localizer does not say)."""


@dataclass(frozen=True)
class Hypotheses:
    """A snapshot of hypotheses for policies and viewers: start poses and normalized weights."""

    poses: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class LocalizerContext:
    """Everything an algorithm is built from."""

    surface: ContactSurface
    motion: MotionModel
    sensor: SensorModel
    step_length: float
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    walls: bool = False
    """Whether a blocked step means the map's edge (`reading_row`)."""


class Localizer(Protocol):
    """An anytime pose estimator over start-pose hypotheses."""

    name: ClassVar[str]

    def start(self, first: Measurement) -> None:
        """First contact: set up the hypotheses."""

    def begin_update(self, measurement: Measurement) -> None:
        """Queue a new measurement; `work` processes it."""

    def work(self, budget: Budget) -> bool:
        """Process within `budget`; True once the queued update is complete."""

    def background(self, budget: Budget) -> bool:
        """This step's share of the work between updates, within `budget`; True once it is
        done (or there is none). Done while the estimate is `pending`, it judges the
        declaration again."""

    def estimate(self) -> Estimate:
        """The current belief."""

    def hypotheses(self, limit: int | None = None) -> Hypotheses:
        """Current hypotheses (at most `limit`, highest weight first)."""


def update(localizer: Localizer, measurement: Measurement) -> None:
    """Run one update to completion."""
    localizer.begin_update(measurement)
    while not localizer.work(Budget.unlimited()):
        pass


def background(localizer: Localizer) -> None:
    """Run this step's background share to the end."""
    while not localizer.background(Budget.unlimited()):
        pass


def settle(localizer: Localizer, estimate: Estimate) -> Estimate:
    """The estimate once the background is done, if the declaration waited only on it
    (`Estimate.pending`): checks that cost a move's worth of waiting cost no move."""
    if not estimate.pending:
        return estimate
    background(localizer)
    return localizer.estimate()


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
