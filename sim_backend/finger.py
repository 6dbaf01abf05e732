"""A simulated rolling fingertip on a known surface: the Backend contract, exact geometry.

The finger's start pose (x, y, heading) and z offset are hidden from the service; it
reports its centre in its own (hand) frame. Heights come from the contact surface of the
world (paper Eq. 7). Steps that would take the centre off the map are blocked. Noise and
model mismatch follow BENCHMARKS.md B2 and are all off by default; every random draw comes
from the generator it is given, so a seed fixes the episode.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from firmware_if.backend import FingerState, HandOfOne, StepCommand, check_can_step
from firmware_if.errors import NotReadyError
from service.errors import ConfigError
from service.localization.models import NoiseSpec, rotate
from service.localization.surface import ContactSurface, HeightMap, contact_surface
from sim_backend.clock import Clock, MonotonicClock
from sim_backend.latch import FaultLatch
from sim_backend.world import perturbed


@dataclass(frozen=True)
class SimConfig:
    """Hidden truth and physics of one simulated finger."""

    start: tuple[float, float, float]
    """Start (x, y, heading) in the map frame: metres, metres, radians."""
    radius: float = 0.008
    z_offset: float = 0.0
    """Map z minus hand z: unknown to the localizer, which only uses relative heights."""
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    step_duration_s: float = 0.0
    """How long a step takes on the simulator's clock (0: done at once)."""

    def __post_init__(self) -> None:
        if len(self.start) != 3 or not np.all(np.isfinite(self.start)):
            raise ConfigError(f"sim start must be three finite numbers, got {self.start}")
        if not self.radius > 0:
            raise ConfigError(f"finger radius must be > 0 metres, got {self.radius}")
        if not self.step_duration_s >= 0:
            raise ConfigError("step_duration_s must be >= 0")


class SimulatedFinger(FaultLatch, HandOfOne):
    """Drop-in simulated finger implementing `firmware_if.backend.Backend`."""

    def __init__(self, world: HeightMap, config: SimConfig, rng: np.random.Generator,
                 clock: Clock | None = None, *, surface: ContactSurface | None = None) -> None:
        """`surface`: the world's contact surface built already (the daemon builds it, and
        perturbs the map, in its compute process; `rng` then continues after that draw)."""
        self.config = config
        self._world_map = world
        self._prebuilt = surface
        self._rng = rng
        self._clock = clock or MonotonicClock()
        self._surface: ContactSurface | None = None
        self._position = np.array(config.start[:2], dtype=np.float64)
        self._reading = np.zeros(3)
        self._torque = False
        self._fault: str | None = None
        self._steps_done = 0
        self._blocked = False
        self._busy_until: int | None = None
        self._pending: tuple[np.ndarray, bool] | None = None

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        noise = self.config.noise
        if self._prebuilt is not None:
            self._surface, world = self._prebuilt, self._prebuilt.map
        else:
            world = perturbed(self._world_map, noise.surface_sigma, noise.surface_correlation,
                              self._rng)
            self._surface = contact_surface(world, self.config.radius)
        x, y, _ = self.config.start
        if not world.inside(np.array(x), np.array(y)):
            raise ConfigError(f"sim start ({x:.4g}, {y:.4g}) m lies outside the map "
                              f"(0..{world.extent[0]:.4g}, 0..{world.extent[1]:.4g})")
        self._reading = self._measure()

    def close(self) -> None:
        self._torque = False
        self._surface = None

    @property
    def pose(self) -> tuple[float, float, float]:
        """Where the fingertip truly is on the map, and the finger's heading: the simulator's
        hidden state, for the record (a reading carries the sensor's noise; a truth moved by
        one was 0.3 mm off the seed's own, a held-out check)."""
        return (float(self._position[0]), float(self._position[1]),
                float(self.config.start[2]))

    # -- I/O -------------------------------------------------------------------------------
    def read_state(self) -> FingerState:
        self._require_open()
        self._finish_step_if_due()
        return FingerState(
            t_ns=self._clock.now_ns(),
            centre=(float(self._reading[0]), float(self._reading[1]), float(self._reading[2])),
            moving=self._busy_until is not None,
            blocked=self._blocked,
            steps_done=self._steps_done,
            torque_on=self._torque,
            fault=self._fault,
        )

    def command_step(self, step: StepCommand) -> None:
        self._require_open()
        check_can_step(fault=self._fault, torque_on=self._torque,
                       busy=self._busy_until is not None)
        noise = self.config.noise
        length = np.hypot(step.dx, step.dy) * (1 + noise.step_length_fraction
                                               * self._rng.standard_normal())
        direction = np.arctan2(step.dy, step.dx) + noise.step_direction_sigma * \
            self._rng.standard_normal()
        mx, my = rotate(np.asarray(self.config.start[2]), length * np.cos(direction),
                        length * np.sin(direction))
        target = self._position + np.array([float(mx), float(my)])
        blocked = not bool(self._surface.map.inside(np.array(target[0]), np.array(target[1])))
        self._pending = (self._position if blocked else target, blocked)
        self._busy_until = self._clock.now_ns() + int(self.config.step_duration_s * 1e9)
        self._finish_step_if_due()

    # -- internals -------------------------------------------------------------------------
    def _cut_step(self) -> None:
        if self._busy_until is None:
            return
        self._busy_until, self._pending = None, None
        self._blocked = True
        self._steps_done += 1
        self._reading = self._measure()

    def _finish_step_if_due(self) -> None:
        if self._busy_until is None or self._clock.now_ns() < self._busy_until:
            return
        position, blocked = self._pending
        self._position = np.asarray(position, dtype=np.float64)
        self._blocked = blocked
        self._steps_done += 1
        self._busy_until = None
        self._pending = None
        self._reading = self._measure()

    def _measure(self) -> np.ndarray:
        """Centre in the hand frame (relative to the start, rotated into the finger's axes)."""
        x0, y0, heading = self.config.start
        rel = self._position - np.array([x0, y0])
        hx, hy = rotate(np.asarray(-heading), rel[0], rel[1])
        z = self._surface.height(self._position[0], self._position[1]) - self.config.z_offset
        centre = np.array([float(hx), float(hy), z])
        sigma = self.config.noise.measurement_sigma
        if sigma:
            centre += sigma * self._rng.standard_normal(3)
        return centre

    def _require_open(self) -> None:
        if self._surface is None:
            raise NotReadyError("simulated finger is not open: call open() first")
