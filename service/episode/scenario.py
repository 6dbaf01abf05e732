"""One localization scenario, declared once: settings, how to build its parts, how to score it.

`haptic run`, every `haptic bench` scenario and the daemon build their map, simulated
finger, localizer and policy through here, so a setting means the same thing everywhere.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from service.bounds import check_fields, check_keywords, setting
from service.errors import ConfigError
from service.localization.localizers.base import Estimate, Localizer, LocalizerContext, wrap_angle
from service.localization.localizers.pose_table import grid_positions
from service.localization.maps import load_map
from service.localization.models import HARDWARE_SENSOR_SIGMA, NoiseSpec, models_for
from service.localization.surface import (
    ContactSurface,
    HeightMap,
    check_radius,
    contact_surface,
)
from service.registry import LOCALIZERS, POLICIES


@dataclass(frozen=True)
class RunSettings:
    """Everything that defines an episode. Defaults are BENCHMARKS.md B1 on `peaks`.

    Each field's type and range is declared here once (`service.bounds`); the daemon's
    `[scenario]` section reuses these declarations."""

    map: str = setting("peaks", "str")
    spacing: float | None = setting(None, "float", lo=1e-6, hi=0.1, unit="m", optional=True)
    radius: float = setting(0.008, "float", lo=1e-4, hi=10.0, unit="m")  # map_check: fit
    step: float = setting(0.01, "float", lo=1e-4, hi=0.1, unit="m")
    algorithm: str = setting("particles", "str", choices=LOCALIZERS.names)
    policy: str = setting("info-gain", "str", choices=POLICIES.names)
    seed: int = setting(0, "int", lo=0, hi=2**63 - 1)
    noise: bool = setting(False, "bool")
    start: tuple[float, float, float] | None = setting(None, "vec3", lo=-1e3, hi=1e3,
                                                       optional=True)
    """(x, y, heading) in metres and radians; None draws one from the seed."""
    max_steps: int = setting(100, "int", lo=1, hi=100_000)
    headings: int = setting(11, "int", lo=1, hi=360)
    sensor_sigma: float | None = setting(None, "float", lo=1e-9, hi=0.01, unit="m",
                                         optional=True)
    """Measurement noise (metres) the localizer assumes; None: what `noise` implies."""
    walls: bool = setting(True, "bool")
    """A blocked step means the map's edge stopped it (the simulated world); on hardware a
    joint limit can too, so there it is no evidence about the pose (`for_backend`)."""
    localizer_options: dict[str, Any] = setting({}, "options")
    planar: bool = False
    """The finger moves in its plane only (a planar chain on servos, `for_backend`): the
    policy offers it no +-y step."""

    def __post_init__(self) -> None:
        check_fields(self, flags=True)  # errors name `haptic run`'s options
        check_keywords(LOCALIZERS.load(self.algorithm), self.localizer_options,
                       f"algorithm '{self.algorithm}'")
        POLICIES.load(self.policy)

    @property
    def noise_spec(self) -> NoiseSpec:
        """B2's models scaled to the step (the paper's unit) when noise is on."""
        return NoiseSpec.realistic(unit=self.step) if self.noise else NoiseSpec()

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Truth:
    x: float
    y: float
    heading: float

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.heading)


def surface_for(settings: RunSettings, height_map: HeightMap | None = None) -> ContactSurface:
    """The contact surface of the settings' map (loaded unless given)."""
    height_map = height_map or load_map(settings.map, settings.spacing)
    return contact_surface(height_map, settings.radius)


def for_backend(settings: RunSettings, backend: str, hand: str | None = None
                ) -> RunSettings:
    """`settings` for a run on `backend` with the finger `hand` (a preset or a file): on
    hardware, unless told otherwise, the localizer assumes the encoders' rounding as noise
    (`HARDWARE_SENSOR_SIGMA`; exact readings would eliminate the truth), a blocked step is
    no evidence of the map's edge, and a planar finger is offered no +-y step."""
    if backend == "sim":
        return settings
    planar = settings.planar
    if hand is not None:
        from firmware_if.errors import HandConfigError
        from firmware_if.hand import load_hand

        with contextlib.suppress(HandConfigError):  # opening the backend tells what is wrong
            planar = load_hand(hand).planar
    return replace(settings, walls=False, planar=planar, sensor_sigma=(
        HARDWARE_SENSOR_SIGMA if settings.sensor_sigma is None else settings.sensor_sigma))


def episode_streams(seed: int) -> list[np.random.Generator]:
    """The four independent random streams of a seeded episode: truth, world, localizer,
    policy. `haptic run`, `hapticd` and `haptic emulate` split a seed only here, so the same
    seed hides the same start pose in all three."""
    return np.random.default_rng(seed).spawn(4)


def check_scenario(settings: RunSettings, height_map: HeightMap) -> None:
    """Refuse what a finger's run on `height_map` cannot do, before any work: the tip's
    radius first (it names a profile's one row), then the start, then the localizer.
    `haptic run` and `haptic campaign` ask alike."""
    check_radius(height_map, settings.radius)
    check_start(settings, height_map)
    check_algorithm(settings, height_map)


def check_algorithm(settings: RunSettings, height_map: HeightMap) -> None:
    """Refuse a localizer the map cannot take, before any work: a held-out campaign of the
    grid localizers over a profile among its maps recorded each of their episodes as an
    error and exited 0."""
    refusal = getattr(LOCALIZERS.load(settings.algorithm), "profiles", None)
    if height_map.is_profile and refusal:
        raise ConfigError(refusal)


def check_start(settings: RunSettings, height_map: HeightMap) -> None:
    """Refuse a start the map cannot give (`draw_truth`), before any work is shown."""
    x_max, y_max = height_map.extent
    if settings.start is not None:
        x, y, heading = settings.start
        if height_map.is_profile and (y != 0 or not np.isclose(np.cos(heading) ** 2, 1.0)):
            raise ConfigError(f"start ({x:.4g}, {y:.4g}, {np.rad2deg(heading):.4g} deg) on "
                              f"profile '{height_map.name}': a planar finger's pose on a "
                              "profile is a position along it, heading 0 or 180 deg, with y "
                              f"0: give --start {x:.4g},0,0 or {x:.4g},0,180")
        if not height_map.inside(np.array(x), np.array(y)):
            raise ConfigError(f"start ({x:.4g}, {y:.4g}) m (`--start`, `scenario.start`) lies "
                              f"outside the map (0..{x_max:.4g}, 0..{y_max:.4g} m)")
        return
    margin = 2 * settings.step
    if settings.noise and (x_max <= 2 * margin
                           or (not height_map.is_profile and y_max <= 2 * margin)):
        raise ConfigError("the map is too small for starts two steps inside its edge; "
                          "use a smaller --step")
    if not settings.noise:
        try:
            grid_positions(height_map, settings.step)
        except ConfigError:
            raise _no_room(settings, height_map) from None


def _no_room(settings: RunSettings, height_map: HeightMap) -> ConfigError:
    """No start to draw noise-free. Not the localizer's table (a held-out check's particles
    run was told of "a pose table"): the one the starts are drawn on."""
    x_max, y_max = height_map.extent
    return ConfigError(f"the map ({x_max:.4g} x {y_max:.4g} m) has no room for the starts a "
                       "noise-free run draws (poses a step apart, a step in from its edges, "
                       f"at --step {settings.step:g} m): give --start (`scenario.start`), a "
                       "shorter --step, or --noise")


def draw_truth(settings: RunSettings, height_map: HeightMap, rng: np.random.Generator) -> Truth:
    """The hidden start pose: a pose-table entry (noise-free, B1) or continuous (noise, B2).

    Continuous starts lie at least two step lengths inside the map's edge.
    """
    check_start(settings, height_map)
    if settings.start is not None:
        x, y, heading = settings.start
        return Truth(float(x), 0.0 if height_map.is_profile else float(y), float(heading))
    if not settings.noise:
        xs, ys = grid_positions(height_map, settings.step)  # room for them: `check_start`
        headings = (np.array([0.0, np.pi]) if height_map.is_profile
                    else np.arange(settings.headings) * 2 * np.pi / settings.headings)
        return Truth(float(rng.choice(xs)), float(rng.choice(ys)), float(rng.choice(headings)))
    x_max, y_max = height_map.extent
    margin = 2 * settings.step
    x = rng.uniform(margin, x_max - margin)
    y = 0.0 if height_map.is_profile else rng.uniform(margin, y_max - margin)
    heading = float(rng.choice([0.0, np.pi])) if height_map.is_profile else rng.uniform(
        0, 2 * np.pi)
    return Truth(float(x), float(y), float(heading))


def prepare_localizers() -> None:
    """Compile the localizers' inner loops now (a second or so on a cold cache), so a
    process with deadlines never compiles inside one."""
    from service.localization import kernels

    kernels.warm_up()


def build_localizer(settings: RunSettings, surface: ContactSurface,
                    rng: np.random.Generator) -> Localizer:
    assumed = (settings.noise_spec if settings.sensor_sigma is None
               else NoiseSpec(measurement_sigma=settings.sensor_sigma))
    motion, sensor = models_for(assumed)
    ctx = LocalizerContext(surface=surface, motion=motion, sensor=sensor,
                           step_length=settings.step, rng=rng, walls=settings.walls)
    cls = LOCALIZERS.load(settings.algorithm)
    options = dict(settings.localizer_options)
    if settings.algorithm == "elimination":
        options.setdefault("headings", settings.headings)
    try:
        return cls(ctx, **options)
    except TypeError as exc:
        raise ConfigError(f"bad option for algorithm '{settings.algorithm}': {exc}") from None


def build_policy(settings: RunSettings):
    return POLICIES.load(settings.policy)()


@dataclass(frozen=True)
class Score:
    position_error: float | None
    heading_error: float | None
    success: bool
    wrong_declaration: bool


def score(estimate: Estimate, truth: Truth, step: float) -> Score:
    """Success: converged within a quarter step and 5 degrees of the truth (BENCHMARKS.md B2)."""
    if estimate.pose is None:
        return Score(None, None, False, False)
    x, y, heading = estimate.pose
    pos_err = float(np.hypot(x - truth.x, y - truth.y))
    head_err = float(abs(wrap_angle(heading - truth.heading)))
    close = bool(pos_err <= 0.25 * step and head_err <= np.deg2rad(5.0))
    converged = bool(estimate.converged)
    return Score(pos_err, head_err, converged and close, converged and not close)
