"""The daemon's configuration, declared once: frozen dataclasses checked on load and on change.

A TOML file (config/hapticd.toml is the annotated sample) maps one table to each section.
Unknown keys are errors, so a typo never silently falls back to a default. Run-time
changes (`configure`, `set_map`, ...) go through `DaemonConfig.updated`, which builds new
dataclasses and so runs the same checks.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.episode.scenario import RunSettings, for_backend
from service.errors import ConfigError
from service.registry import BACKENDS, LOCALIZERS, POLICIES
from service.wire.envelope import MAX_FRAME_BYTES

OVERRUN_POLICIES = ("skip", "catch_up")
LOCALIZER_MODES = ("sliced", "thread")
RUNTIME_SECTIONS = ("backend", "scenario", "loop", "lease")
"""Sections `configure` may change while the daemon runs; endpoints and security need a restart."""


def _positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class BackendConfig:
    """Which backend (a BACKENDS registry name) and the simulator's settings."""

    name: str = "sim"
    step_duration_s: float = 0.05
    """Simulated step time: steps take real time so the loop sees them in progress."""
    options: dict[str, Any] = field(default_factory=dict)
    """A hardware backend's settings, e.g. dynamixel: {port, hand} (its `from_cli` builder)."""

    def __post_init__(self) -> None:
        if self.name not in BACKENDS.names():
            raise ConfigError(f"backend.name '{self.name}' is unknown; choose one of: "
                              f"{', '.join(BACKENDS.names())}")
        if not (isinstance(self.step_duration_s, (int, float)) and self.step_duration_s >= 0):
            raise ConfigError("backend.step_duration_s must be >= 0 seconds")
        if not isinstance(self.options, dict):
            raise ConfigError("backend.options must be a table")


@dataclass(frozen=True)
class ScenarioConfig:
    """Map, finger, localizer and policy: the same meaning as `haptic run`'s settings."""

    map: str = "peaks"
    spacing: float | None = None
    radius: float = 0.008
    step: float = 0.01
    localizer: str = "particles"
    policy: str = "info-gain"
    headings: int = 11
    max_steps: int = 100
    noise: bool = False
    seed: int = 0
    start: tuple[float, float, float] | None = None
    """Simulator only: the hidden start pose; None draws one from the seed."""
    localizer_options: dict[str, Any] = field(default_factory=dict)
    sensor_sigma: float | None = None
    """Measurement noise (m) the localizer assumes; None: from `noise`, or
    HARDWARE_SENSOR_SIGMA on a hardware backend."""

    def __post_init__(self) -> None:
        if self.localizer not in LOCALIZERS.names():
            raise ConfigError(f"scenario.localizer '{self.localizer}' is unknown; choose one "
                              f"of: {', '.join(LOCALIZERS.names())}")
        if self.policy not in POLICIES.names():
            raise ConfigError(f"scenario.policy '{self.policy}' is unknown; choose one of: "
                              f"{', '.join(POLICIES.names())}")
        if self.start is not None:
            if not (isinstance(self.start, (list, tuple)) and len(self.start) == 3):
                raise ConfigError("scenario.start must be [x, y, heading] (m, m, rad)")
            object.__setattr__(self, "start", tuple(float(v) for v in self.start))
        self.run_settings()  # RunSettings carries the numeric checks

    def run_settings(self) -> RunSettings:
        try:
            return RunSettings(map=self.map, spacing=self.spacing, radius=self.radius,
                               step=self.step, algorithm=self.localizer, policy=self.policy,
                               seed=self.seed, noise=self.noise, start=self.start,
                               max_steps=self.max_steps, headings=self.headings,
                               localizer_options=dict(self.localizer_options),
                               sensor_sigma=self.sensor_sigma)
        except TypeError as exc:
            raise ConfigError(f"scenario: {exc}") from None


@dataclass(frozen=True)
class LoopConfig:
    """The real-time loop: rate, per-tick localizer budget, overrun policy, stream rates."""

    rate_hz: float = 200.0
    work_fraction: float = 0.5
    """Share of a period the localizer may use in one tick."""
    overrun: str = "skip"
    """'skip': after an overrun resume at the next period boundary; 'catch_up': run late ticks."""
    cloud_hz: float = 4.0
    state_every: int = 1
    """Publish `state` every N ticks."""
    cloud_points: int = 500
    stats_window: int = 1000
    """Ticks the `state` timing percentiles cover."""
    localizer_mode: str = "sliced"
    """'sliced': anytime `work` under each tick's budget; 'thread': whole updates on a
    worker thread, for localizers whose slices are longer than a tick."""

    def __post_init__(self) -> None:
        _positive("loop.rate_hz", self.rate_hz)
        if self.rate_hz > 2000:
            raise ConfigError("loop.rate_hz above 2000 is not supported")
        if not 0 < self.work_fraction <= 0.9:
            raise ConfigError("loop.work_fraction must be in (0, 0.9]")
        if self.overrun not in OVERRUN_POLICIES:
            raise ConfigError(f"loop.overrun must be one of {OVERRUN_POLICIES}")
        _positive("loop.cloud_hz", self.cloud_hz)
        if self.localizer_mode not in LOCALIZER_MODES:
            raise ConfigError(f"loop.localizer_mode must be one of {LOCALIZER_MODES}")
        for name in ("state_every", "cloud_points", "stats_window"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"loop.{name} must be an integer >= 1")

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.rate_hz))


@dataclass(frozen=True)
class EndpointConfig:
    pub: str = "tcp://127.0.0.1:5560"
    cmd: str = "tcp://127.0.0.1:5561"
    sndhwm: int = 1000
    """Messages queued per subscriber before PUB drops for that subscriber."""
    max_request_bytes: int = 64 * 1024

    def __post_init__(self) -> None:
        for name in ("pub", "cmd"):
            value = getattr(self, name)
            if not isinstance(value, str) or "://" not in value:
                raise ConfigError(f"endpoints.{name} must be a ZeroMQ endpoint like "
                                  f"tcp://127.0.0.1:5560, got {value!r}")
        if not (isinstance(self.sndhwm, int) and self.sndhwm >= 1):
            raise ConfigError("endpoints.sndhwm must be an integer >= 1")
        if not (isinstance(self.max_request_bytes, int)
                and 256 <= self.max_request_bytes <= MAX_FRAME_BYTES):
            raise ConfigError("endpoints.max_request_bytes must be 256 .. 16 MiB")


@dataclass(frozen=True)
class SecurityConfig:
    """CurveZMQ: required for any non-loopback bind (checked by service.wire.security)."""

    curve: bool = False
    server_secret_key: str = ""
    """Path of the server's `.key_secret` file (from `haptic keygen`)."""
    authorized_clients: str = ""
    """Directory of client `.key` files allowed to connect."""

    def __post_init__(self) -> None:
        if self.curve and not (self.server_secret_key and self.authorized_clients):
            raise ConfigError("security.curve needs server_secret_key and authorized_clients")


@dataclass(frozen=True)
class LeaseConfig:
    ttl_s: float = 3.0
    """A controller that sends nothing for this long loses control."""
    hold_s: float = 1.0
    """After the lease expires an active finger holds still this long, then torque goes off."""

    def __post_init__(self) -> None:
        _positive("lease.ttl_s", self.ttl_s)
        if not (isinstance(self.hold_s, (int, float)) and self.hold_s >= 0):
            raise ConfigError("lease.hold_s must be >= 0 seconds")


@dataclass(frozen=True)
class DaemonConfig:
    backend: BackendConfig = field(default_factory=BackendConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    endpoints: EndpointConfig = field(default_factory=EndpointConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    lease: LeaseConfig = field(default_factory=LeaseConfig)
    auto_configure: bool = True
    """Open the backend at start-up (state inactive) instead of waiting for `configure`."""

    def run_settings(self) -> RunSettings:
        """The scenario's settings; on hardware the localizer assumes encoder-level noise."""
        return for_backend(self.scenario.run_settings(), self.backend.name)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def updated(self, changes: dict[str, Any],
                sections: tuple[str, ...] = RUNTIME_SECTIONS) -> DaemonConfig:
        """A new, validated config with `{section: {key: value}}` applied."""
        if not isinstance(changes, dict):
            raise ConfigError("changes must be a map of section -> {key: value}")
        parts = {}
        for name, values in changes.items():
            if name not in sections:
                raise ConfigError(f"section '{name}' cannot be changed here; changeable: "
                                  f"{', '.join(sections)}")
            parts[name] = _section(type(getattr(self, name)), name, values,
                                   base=getattr(self, name))
        return dataclasses.replace(self, **parts)


SECTIONS = {f.name: f for f in dataclasses.fields(DaemonConfig)}


def _section(cls: type, name: str, values: Any, base: Any = None) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"[{name}] must be a table")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(f"[{name}] has unknown key(s) {', '.join(unknown)}; known: "
                          f"{', '.join(sorted(known))}")
    try:  # ScenarioConfig turns a `start` list into a tuple itself
        return dataclasses.replace(base, **values) if base is not None else cls(**values)
    except TypeError as exc:
        raise ConfigError(f"[{name}]: {exc}") from None


def from_dict(data: dict[str, Any]) -> DaemonConfig:
    """A validated config from parsed TOML (or any nested dict)."""
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"unknown config section(s) {', '.join(unknown)}; known: "
                          f"{', '.join(SECTIONS)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        if name == "auto_configure":
            if not isinstance(value, bool):
                raise ConfigError("auto_configure must be true or false")
            kwargs[name] = value
        else:
            cls = type(getattr(DaemonConfig(), name))
            kwargs[name] = _section(cls, name, value)
    return DaemonConfig(**kwargs)


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate a TOML config file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config file '{path}' does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file '{path}' could not be read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file '{path}' is not valid TOML: {exc}") from None
    return from_dict(data)
