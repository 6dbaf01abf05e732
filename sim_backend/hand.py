"""A simulated hand holding a planar object: hidden pose, gravity, quasi-static grasp.

The object's pose (x, z, theta) in the hand plane is hidden from the service; the hand
reports every fingertip centre in its own frame. The model is quasi-static: while the grasp
resists the object's weight plus a disturbance margin (`grasp.hand_quality`), the object
stays put; a move after which - or part-way through which - the margin is lost makes it
slip out. That is a drop: the hand reports it and refuses further steps.

A step moves one finger: its centre goes by the commanded displacement (with B2's length
and direction noise) and, compliant, presses back onto the object, rolling along it while
the others hold. A manipulation moves every finger and turns the tips: the object goes where
the rolling contacts carry it (`objects.rolling.carry`, with noise on each substep's
motion). A commanded target beyond a finger's reach is refused before anything moves
(`blocked`), as the hand's controller knows its joint limits. Readings carry B2's
measurement noise; the world's outline differs from the model's by B2's smooth
perturbation. Every random draw comes from the generator given, so a seed fixes the run.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from firmware_if import kinematics as kin
from firmware_if.backend import (
    FingerState,
    HandCommand,
    HandState,
    PlanarHand,
    check_hand_command,
)
from firmware_if.errors import NotReadyError
from firmware_if.hand import Finger, Hand
from service.errors import ConfigError
from service.localization import chain_kernels
from service.localization.grasp import GraspSpec, hand_quality, joint_torque
from service.localization.models import NoiseSpec
from service.localization.objects import kernels, rolling
from service.localization.objects.contour import Contour
from service.localization.objects.field import ContactField, contact_field
from sim_backend.clock import Clock, MonotonicClock
from sim_backend.latch import FaultLatch


@dataclass(frozen=True)
class HandSimConfig:
    """Hidden truth and physics of one simulated hand and object."""

    pose: tuple[float, float, float]
    """The object's (x, z, theta) in the hand plane: metres, metres, radians."""
    grasp: GraspSpec = field(default_factory=GraspSpec)
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    fixed: bool = False
    """The object is clamped in place (no weight, no drop): one finger may explore it."""
    substeps: int = 8
    """Quality is checked this many times along every move."""
    step_duration_s: float = 0.0

    def __post_init__(self) -> None:
        if len(self.pose) != 3 or not np.all(np.isfinite(self.pose)):
            raise ConfigError(f"object pose must be three finite numbers, got {self.pose}")
        if self.substeps < 1:
            raise ConfigError("substeps must be >= 1")
        if not self.step_duration_s >= 0:
            raise ConfigError("step_duration_s must be >= 0")


def perturbed_contour(contour: Contour, sigma: float, correlation: float,
                      rng: np.random.Generator) -> Contour:
    """The outline moved along its normals by smooth noise of sd `sigma` metres, correlated
    over about `correlation` metres of arc (B2's model mismatch); same frame as `contour`."""
    if sigma == 0:
        return contour
    spacing = 0.0005
    points, normals = contour.resampled(spacing)
    noise = ndimage.gaussian_filter1d(rng.standard_normal(len(points)),
                                      max(correlation / spacing, 1e-6), mode="wrap")
    noise *= sigma / max(noise.std(), 1e-300)
    return Contour(points=points + noise[:, None] * normals, name=f"{contour.name}+world",
                   origin=contour.origin, axis=contour.axis)


def close_fingers(fingers: Sequence[Finger], field: ContactField, pose: np.ndarray
                  ) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """Each fingertip brought from its finger's base straight towards the object's centroid
    until it touches: centres (n, 2) and joint angles, or None if a finger cannot reach."""
    centres, angles = [], []
    for finger in fingers:
        base = np.array(finger.base[:2])
        ray = np.asarray(pose[:2]) - base
        length = float(np.hypot(*ray))
        s = np.linspace(0.0, length, int(length / 0.0005) + 2)
        points = base + s[:, None] * ray / length
        gap = kernels.residuals(*field.args, np.asarray(pose, dtype=np.float64)[None], points,
                                np.full(len(points), finger.radius))[0]
        touching = np.flatnonzero(gap <= 0)
        if len(touching) == 0:
            return None
        first = points[max(touching[0] - 1, 0)]
        centre = rolling.settle(field, pose[None], first[None, None, :],
                                np.array([finger.radius]))[0, 0]
        q = kin.inverse(finger, np.array([centre[0], 0.0, centre[1]]), np.array(finger.home),
                        iterations=300)
        if not bool(q.reachable):
            return None
        centres.append(centre)
        angles.append(q.q)
    return np.array(centres), angles


class _Dropped(Exception):
    """The grasp lost its margin part-way through a move."""


class SimulatedHand(PlanarHand, FaultLatch):
    """A simulated hand and object, implementing `firmware_if.backend.Backend`."""

    def __init__(self, hand: Hand, contour: Contour, config: HandSimConfig,
                 rng: np.random.Generator, clock: Clock | None = None,
                 world: Contour | None = None) -> None:
        """`world`: the outline as the fingers meet it, if already drawn (the seed's start
        was chosen in it); None: `contour` perturbed by the config's noise at each open."""
        self.hand = hand
        self.contour = contour
        self._world = world
        self.config = config
        self._rng = rng
        self._clock = clock or MonotonicClock()
        self.fingers = hand.fingers
        self._radii = np.array([f.radius for f in self.fingers])
        self._torque_nm = joint_torque(hand.goal_current_a, self.fingers[0].joints[0].model)
        self._field: ContactField | None = None
        self._pose = np.array(config.pose, dtype=np.float64)
        self._centres = np.zeros((len(self.fingers), 2))
        self._q: list[np.ndarray] = []
        self._readings = np.zeros((len(self.fingers), 2))
        self._rolls = np.zeros(len(self.fingers))
        self._torque = False
        self._fault: str | None = None
        self._dropped = False
        self._blocked = False
        self._steps_done = 0
        self._busy_until: int | None = None
        self._motion: Iterator[None] | None = None
        """The step under way, a substep per `next`."""
        self.quality = float("nan")
        """The grasp's true quality now (newtons): for scoring and figures, not the service."""
        self.min_quality = float("inf")
        """The least true quality seen at any substep of any move."""
        self.step_min_quality = float("nan")
        """The least true quality at the substeps of the last move, where it ended included
        (a turn may dip far below where it ends)."""

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        self._motion, self._busy_until = None, None  # opened again without a close
        noise = self.config.noise
        world = self._world
        if world is None:
            world = perturbed_contour(self.contour, noise.surface_sigma,
                                      noise.surface_correlation, self._rng)
        self._field = contact_field(world)
        grasp = close_fingers(self.fingers, self._field, self._pose)
        if grasp is None:
            raise ConfigError(f"hand '{self.hand.name}' cannot reach object "
                              f"'{self.contour.name}' at pose {np.round(self._pose, 4)}")
        self._centres, self._q = grasp
        self.quality = self._quality(self._pose, self._centres, self._q)
        if not self.config.fixed and self.quality < self.config.grasp.margin_n:
            raise ConfigError(f"hand '{self.hand.name}' cannot hold object "
                              f"'{self.contour.name}' at pose {np.round(self._pose, 4)}: "
                              f"grasp quality {self.quality:.3f} N is below the margin")
        self.min_quality = self.step_min_quality = self.quality
        self._reachable(self._centres)  # loads the compiled IK now, not in a step's tick
        self._measure()

    def close(self) -> None:
        """Torque off; a step under way ends here, undone (it never happens)."""
        self._torque = False
        self._field = None
        self._motion, self._busy_until = None, None

    @property
    def pose(self) -> tuple[float, float, float]:
        """The object's true pose now (for scoring; the service never sees it)."""
        return tuple(float(v) for v in self._pose)  # type: ignore[return-value]

    @property
    def dropped(self) -> bool:
        return self._dropped

    @property
    def centres(self) -> np.ndarray:
        """The fingertip centres' true places (n, 2), without measurement noise."""
        return self._centres.copy()

    @property
    def steps_done(self) -> int:
        return self._steps_done

    def reported(self) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """What the hand reads now: centres (n, 2) with their measurement noise, the joint
        angles that put each finger's centre at its true place, and the tips' roll angles.
        (A plant on the servo bus turns these into encoder values.)"""
        return self._readings.copy(), [q.copy() for q in self._q], self._rolls.copy()

    # -- I/O -------------------------------------------------------------------------------
    def read_hand(self) -> HandState:
        self._require_open()
        self._advance(everything=False)
        self._finish_step_if_due()
        moving = self._busy_until is not None
        fingers = tuple(
            FingerState(t_ns=self._clock.now_ns(),
                        centre=(float(r[0]), 0.0, float(r[1])), moving=moving,
                        blocked=self._blocked, steps_done=self._steps_done,
                        joints=tuple(float(a) for a in q), tip_roll=float(roll),
                        torque_on=self._torque, fault=self._fault)
            for r, q, roll in zip(self._readings, self._q, self._rolls, strict=True))
        return HandState(t_ns=self._clock.now_ns(), fingers=fingers, dropped=self._dropped)

    def command_hand(self, command: HandCommand) -> None:
        """Start a step: checked and its reach tested now; its motion worked out one
        substep per `read_hand` (the daemon reads once a tick, so no tick carries a whole
        step's physics), and all of what is left once the step is due."""
        self._require_open()
        check_hand_command(command, hand=self.hand.name, fingers=len(self.fingers),
                           fault=self._fault, torque_on=self._torque,
                           busy=self._busy_until is not None, dropped=self._dropped)
        moving = command.moving
        moves = np.array([[0.0, 0.0] if m is None else [m.dx, m.dz] for m in command.moves])
        rolls = np.array([0.0 if m is None else m.roll for m in command.moves])
        explore = len(moving) == 1 and rolls[moving[0]] == 0.0
        if not explore and self.config.fixed:
            raise NotReadyError("the object is clamped in place: it cannot be manipulated")
        self._blocked = not self._reachable(self._centres + moves)
        self.step_min_quality = self.quality if self._blocked else float("inf")
        if not self._blocked:
            self._motion = (self._explore(moving[0], moves[moving[0]]) if explore
                            else self._manipulate(moves, rolls))
        self._busy_until = self._clock.now_ns() + int(self.config.step_duration_s * 1e9)
        self._finish_step_if_due()

    # -- physics ---------------------------------------------------------------------------
    def _advance(self, *, everything: bool) -> None:
        """One substep of the motion under way, or all that is left."""
        while self._motion is not None:
            try:
                next(self._motion)
            except StopIteration:
                self._motion = None
            except _Dropped:
                self._dropped, self._motion = True, None
            if not everything:
                return

    def _explore(self, i: int, move: np.ndarray) -> Iterator[None]:
        """Finger i's step, a substep per iteration; the noise is drawn at the first."""
        noise = self.config.noise
        length = np.hypot(*move) * (1 + noise.step_length_fraction * self._rng.standard_normal())
        heading = np.arctan2(move[1], move[0]) + noise.step_direction_sigma * \
            self._rng.standard_normal()
        realized = length * np.array([np.cos(heading), np.sin(heading)])
        start = self._centres[i].copy()
        centres, q = self._centres.copy(), list(self._q)
        for k in range(1, self.config.substeps + 1):
            aim = start + realized * k / self.config.substeps
            centres[i] = rolling.settle(self._field, self._pose[None], aim[None, None, :],
                                        self._radii[i:i + 1])[0, 0]
            q[i] = self._ik(i, centres[i], q[i])
            self._check(self._pose, centres, q)
            if k < self.config.substeps:
                yield
        self._rolls[i] += float(np.hypot(*(centres[i] - start))) / self._radii[i]
        self._centres, self._q = centres, q

    def _manipulate(self, moves: np.ndarray, rolls: np.ndarray) -> Iterator[None]:
        """Every finger's move carrying the object, a substep per iteration."""
        q = list(self._q)
        noise = self.config.noise
        steps = rolling.carry_steps(
            self._field, self._pose[None], self._centres[None], self._radii, moves, rolls,
            substeps=self.config.substeps, rng=self._rng,
            noise=rolling.TwistNoise(noise.step_length_fraction, noise.step_direction_sigma))
        poses, centres = self._pose[None], self._centres[None]
        for k, (poses, centres) in enumerate(steps):
            for i in range(len(self.fingers)):
                q[i] = self._ik(i, centres[0, i], q[i])
            self._check(poses[0], centres[0], q)
            if k < self.config.substeps - 1:
                yield
        self._pose, self._centres, self._q = poses[0], centres[0], q
        self._rolls += rolls

    def _check(self, pose: np.ndarray, centres: np.ndarray, q: list[np.ndarray]) -> None:
        if self.config.fixed:
            return
        quality = self._quality(pose, centres, q)
        self.quality = quality
        self.min_quality = min(self.min_quality, quality)
        self.step_min_quality = min(self.step_min_quality, quality)
        if quality < self.config.grasp.margin_n:
            raise _Dropped

    def _quality(self, pose: np.ndarray, centres: np.ndarray, q: list[np.ndarray]) -> float:
        return float(hand_quality(self._field, pose[None], centres[None], self.fingers,
                                  q, self._torque_nm, self.config.grasp)[0])

    def _ik(self, i: int, centre: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """`kinematics.inverse`, compiled: the physics of a step is mostly IK, and it runs
        in the daemon's tick."""
        q, _ = chain_kernels.inverse(self.fingers[i], np.array([[centre[0], 0.0, centre[1]]]),
                                     np.asarray(q0, dtype=np.float64)[None])
        return q[0]

    def _reachable(self, targets: np.ndarray) -> bool:
        return all(bool(chain_kernels.inverse(f, np.array([[t[0], 0.0, t[1]]]),
                                              np.asarray(q, dtype=np.float64)[None],
                                              iterations=200)[1][0])
                   for f, t, q in zip(self.fingers, targets, self._q, strict=True))

    def _cut_step(self) -> None:
        if self._busy_until is None:
            return
        self._motion, self._busy_until = None, None  # the substeps made so far stay made
        self._blocked = True
        self._steps_done += 1
        self._measure()

    def _finish_step_if_due(self) -> None:
        if self._busy_until is None or self._clock.now_ns() < self._busy_until:
            return
        self._advance(everything=True)
        self._busy_until = None
        self._steps_done += 1
        self._measure()

    def _measure(self) -> None:
        sigma = self.config.noise.measurement_sigma
        self._readings = self._centres + (sigma * self._rng.standard_normal(self._centres.shape)
                                          if sigma else 0.0)

    def _require_open(self) -> None:
        if self._field is None:
            raise NotReadyError("simulated hand is not open: call open() first")
