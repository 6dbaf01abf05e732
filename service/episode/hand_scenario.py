"""One hand-and-object scenario, declared once: settings, its parts, how to score it.

`haptic run --object`, `haptic bench grasp` (B6) and their tests build the object, the
simulated hand, the object localizer and the grasp-gated policy through here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from firmware_if.hand import Hand, load_hand
from service.episode.scenario import episode_streams
from service.errors import ConfigError
from service.localization.grasp import GraspSpec, hand_quality, joint_torque
from service.localization.localizers.base import Estimate, wrap_angle
from service.localization.localizers.object_base import ObjectContext
from service.localization.models import HARDWARE_SENSOR_SIGMA, NoiseSpec, models_for
from service.localization.objects.contour import Contour, check_fits
from service.localization.objects.field import ContactField, contact_field
from service.localization.objects.files import load_object
from service.localization.objects.rolling import TwistNoise
from service.localization.policies.grasp_gated import GraspGatedPolicy
from service.registry import OBJECT_LOCALIZERS

UNIT = 0.01
"""The paper's unit (metres): B2's noise and the success tolerance scale with it."""
START_OFFSET = 0.003
"""Metres: how far from the hand's grasp centre the object may sit at the start."""


@dataclass(frozen=True)
class HandSettings:
    """Everything that defines a hand episode. Defaults: two fingers on `keyed`."""

    object: str = "keyed"
    plane: str | None = None
    units: str = "m"
    hand: str = "two-finger"
    algorithm: str = "particles"
    seed: int = 0
    noise: bool = False
    step: float = 0.003
    """Metres a finger rolls per exploring step."""
    max_steps: int = 60
    mu: float = 0.5
    mass_kg: float = 0.05
    margin_n: float = 0.2
    threshold_n: float = 1.0
    start_n: float | None = None
    """The quality the hand starts with at least (`GraspSpec.start_n`; None: the
    threshold)."""
    gate: bool = True
    single_finger: bool = False
    """Only the hand's first finger, the object clamped in place (the comparison B6 asks)."""
    start: tuple[float, float, float] | None = None
    """The object's (x, z, theta) at the start; None draws one from the seed."""
    sensor_sigma: float | None = None
    """Measurement noise (metres) the localizer assumes; None: what `noise` implies (on
    servos, noise-free runs assume the encoders' rounding: `HARDWARE_SENSOR_SIGMA`)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.step) and 0 < self.step <= 0.02):
            raise ConfigError("the roll per step (--roll, scenario.roll) must be in (0, 0.02] "
                              f"metres, got {self.step}")
        if self.max_steps < 1:
            raise ConfigError(f"--max-steps must be at least 1, got {self.max_steps}")
        if self.seed < 0:
            raise ConfigError(f"--seed must be >= 0, got {self.seed}")
        if self.sensor_sigma is not None and not 1e-9 <= self.sensor_sigma <= 0.01:
            raise ConfigError(f"sensor_sigma must be in [1e-9, 0.01] m, got {self.sensor_sigma}")
        OBJECT_LOCALIZERS.load(self.algorithm)
        self.grasp  # noqa: B018 - validates friction, mass, margin and threshold

    @property
    def grasp(self) -> GraspSpec:
        return GraspSpec(mu=self.mu, mass_kg=self.mass_kg, margin_n=self.margin_n,
                         threshold_n=self.threshold_n, start_n=self.start_n)

    @property
    def noise_spec(self) -> NoiseSpec:
        return NoiseSpec.realistic(unit=UNIT) if self.noise else NoiseSpec()

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def hand_for_backend(settings: HandSettings, backend: str) -> HandSettings:
    """`settings` for a run on `backend`: on servos, noise-free runs assume the encoders'
    rounding (exact readings would eliminate the truth on it)."""
    if backend == "sim" or settings.sensor_sigma is not None or settings.noise:
        return settings
    return dataclasses.replace(settings, sensor_sigma=HARDWARE_SENSOR_SIGMA)


@dataclass(frozen=True)
class HandParts:
    """The loaded object and hand, shared by every episode of the same settings."""

    contour: Contour
    field: ContactField
    hand: Hand

    @property
    def torque(self) -> float:
        return joint_torque(self.hand.goal_current_a, self.hand.fingers[0].joints[0].model)


def load_parts(settings: HandSettings) -> HandParts:
    """Object and hand of the settings, the object checked against the tips' radius."""
    contour = load_object(settings.object, plane=settings.plane, units=settings.units)
    hand = load_hand(settings.hand, holding=True)
    if len(hand.fingers) < 2:  # it said "found no hold ... too big, too small or too slippery"
        raise ConfigError(f"hand '{settings.hand}' has one finger: holding an object needs a "
                          "hand of several fingers (e.g. two-finger or three-finger)")
    if settings.single_finger:
        hand = dataclasses.replace(hand, fingers=hand.fingers[:1])
    for finger in hand.fingers:
        check_fits(contour, finger.radius)
    return HandParts(contour=contour, field=contact_field(contour), hand=hand)


def draw_truth(settings: HandSettings, parts: HandParts, rng: np.random.Generator,
               world: Contour) -> tuple[float, float, float]:
    """The object's hidden start pose: near the grasp centre, any heading, and such that
    every finger reaches it and (unless clamped) the grasp has the quality the policy
    relies on at the start (`GraspSpec.start_quality_n`).

    Both are judged on `world`, the outline as the hand really meets it (the simulator's:
    the model's perturbed by B2's mismatch, or the model's itself without noise): the
    start's promise is about the hand in the world, and on the model's outline a start
    could hold that the world's drops (`hand_episode.seeded_world` draws both)."""
    from sim_backend.hand import close_fingers  # the simulator's closing motion, by name

    field = contact_field(world)
    centre = np.asarray(parts.hand.grasp_centre)
    spec = settings.grasp
    best = -np.inf  # the best quality of a hold that reached, for the refusal
    for _ in range(200):
        if settings.start is not None:
            pose = np.asarray(settings.start, dtype=np.float64)
        else:
            pose = np.array([*(centre + rng.uniform(-START_OFFSET, START_OFFSET, 2)),
                             rng.uniform(-np.pi, np.pi)])
        grasp = close_fingers(parts.hand.fingers, field, pose)
        if grasp is not None:
            if settings.single_finger:
                return tuple(float(v) for v in pose)  # type: ignore[return-value]
            tips, angles = grasp
            quality = float(hand_quality(field, pose[None], tips[None],
                                         parts.hand.fingers, angles, parts.torque, spec)[0])
            best = max(best, quality)
            if quality >= spec.start_quality_n:
                return tuple(float(v) for v in pose)  # type: ignore[return-value]
        if settings.start is not None:
            raise ConfigError(f"at --start {settings.start} hand '{parts.hand.name}' cannot "
                              f"hold object '{parts.contour.name}' with quality "
                              f"{spec.start_quality_n} N (--start-quality)")
    raise ConfigError(f"hand '{parts.hand.name}' found no hold on object "
                      f"'{parts.contour.name}' in 200 tries: "
                      + _why_no_hold(parts, field, centre, best, spec))


def _why_no_hold(parts: HandParts, field: ContactField, centre: np.ndarray, best: float,
                 spec: GraspSpec) -> str:
    """What kept every try from holding, in words: fingers that reach the object at no
    heading (a base or links wrong), else a grip too weak for the threshold (the mass,
    friction or threshold), else the object's size. The same words for all of them left
    a researcher guessing."""
    from sim_backend.hand import close_fingers

    headings = np.linspace(-np.pi, np.pi, 12, endpoint=False)
    never = [f.name for f in parts.hand.fingers
             if all(close_fingers([f], field, np.array([*centre, h])) is None
                    for h in headings)]
    if never:
        return (f"finger{'s' if len(never) > 1 else ''} {', '.join(map(repr, never))} "
                f"reach{'' if len(never) > 1 else 'es'} no part of it held at the grasp "
                f"centre ({centre[0] * 1e3:.1f}, {centre[1] * 1e3:.1f}) mm: check the "
                "finger's base and links (metres) in the hand file")
    if np.isfinite(best):
        return (f"the firmest hold found has a quality of {best:.2f} N, below the "
                f"{spec.start_quality_n:g} N the start needs (--start-quality, "
                f"--threshold): a lighter object (--mass), more friction (--mu) or a lower "
                "threshold")
    return "every finger reaches it alone, but never all at once: " + _size_words(parts, centre)


def _size_words(parts: HandParts, centre: np.ndarray) -> str:
    """Whether the object is too big or too small for the hand, in words: the fingers close
    on it scaled down or up (a held-out check's 113 mm square was "too big or too small")."""
    from sim_backend.hand import close_fingers

    headings = np.linspace(-np.pi, np.pi, 12, endpoint=False)
    width = parts.contour.extent * 1e3
    for factor, words in ((0.5, "too big"), (2.0, "too small")):
        scaled = contact_field(dataclasses.replace(parts.contour,
                                                   points=parts.contour.points * factor))
        if any(close_fingers(parts.hand.fingers, scaled, np.array([*centre, h])) is not None
               for h in headings):
            return (f"it is {words} for this hand ({width:.0f} mm across; it would hold "
                    f"one {'half' if factor < 1 else 'twice'} that size)")
    return (f"it is too big or too small for this hand ({width:.0f} mm across; it would "
            "hold one neither half nor twice that size)")


def streams(seed: int) -> list[np.random.Generator]:
    """Truth, world, localizer and policy streams: as `scenario.episode_streams`."""
    return episode_streams(seed)


def build_localizer(settings: HandSettings, parts: HandParts, rng: np.random.Generator):
    noise = settings.noise_spec
    _, sensor = models_for(noise if settings.sensor_sigma is None
                           else NoiseSpec(measurement_sigma=settings.sensor_sigma))
    ctx = ObjectContext(field=parts.field,
                        radii=np.array([f.radius for f in parts.hand.fingers]),
                        sensor=sensor,
                        motion=TwistNoise(noise.step_length_fraction, noise.step_direction_sigma),
                        scale=UNIT, rng=rng,
                        mismatch_length=noise.surface_correlation if noise.surface_sigma else 0.0,
                        mismatch_sd=noise.surface_sigma)
    return OBJECT_LOCALIZERS.load(settings.algorithm)(ctx)


def build_policy(settings: HandSettings) -> GraspGatedPolicy:
    return GraspGatedPolicy(gate=settings.gate)


@dataclass(frozen=True)
class HandScore:
    position_error: float | None
    heading_error: float | None
    success: bool
    wrong_declaration: bool


def score(estimate: Estimate | None, truth: tuple[float, float, float], dropped: bool
          ) -> HandScore:
    """Success: converged, not dropped, within a quarter unit and 5 degrees of the object's
    true pose at the end (B2's tolerance)."""
    if estimate is None or estimate.pose is None:
        return HandScore(None, None, False, False)
    x, z, heading = estimate.pose
    pos_err = float(np.hypot(x - truth[0], z - truth[1]))
    head_err = float(abs(wrap_angle(heading - truth[2])))
    close = bool(pos_err <= 0.25 * UNIT and head_err <= np.deg2rad(5.0))
    converged = bool(estimate.converged)
    return HandScore(pos_err, head_err, converged and close and not dropped,
                     converged and not close)
