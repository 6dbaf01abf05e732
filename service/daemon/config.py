"""The daemon's configuration, declared once: frozen dataclasses checked on load and on change.

A TOML file (config/hapticd.toml is the annotated sample) maps one table to each section.
Unknown keys are errors, so a typo never silently falls back to a default. Run-time
changes (`configure`, `set_map`, ...) go through `DaemonConfig.updated`, which builds new
dataclasses and so runs the same checks.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from firmware_if.dynamixel_backend import check_cycle_budget
from firmware_if.errors import HandConfigError
from firmware_if.hand import load_hand
from service.bounds import check_fields, check_keywords, same_as, setting
from service.daemon.port_choice import check_patterns
from service.daemon.quiet_files import quiet_hand_error
from service.episode.hand_scenario import HandSettings, hand_for_backend
from service.episode.scenario import RunSettings, for_backend
from service.errors import ConfigError, MapError, ObjectError
from service.localization.maps import MAP_FILE_SUFFIXES, check_map_spec
from service.localization.objects.files import check_object_spec
from service.registry import BACKENDS
from service.wire.envelope import MAX_FRAME_BYTES
from service.wire.security import port_of

OVERRUN_POLICIES = ("skip", "catch_up")
REMOVED = {("loop", "work_fraction"): "the localizer no longer works inside ticks",
           ("loop", "localizer_mode"): "the localizer always runs in a process of its own"}
"""Keys of earlier versions, named in the error instead of 'unknown'."""
RUNTIME_SECTIONS = ("backend", "scenario", "loop", "lease")
"""Sections `configure` may change while the daemon runs; endpoints and security need a restart."""
BACKEND_BUILDER_ARGS = ("radius", "step")
"""Arguments of a hardware backend's `from_cli` that come from [scenario], not its options."""


@dataclass(frozen=True)
class BackendConfig:
    """Which backend (a BACKENDS registry name) and the simulator's settings."""

    name: str = setting("sim", "str", choices=BACKENDS.names)
    step_duration_s: float = setting(0.05, "float", lo=0.0, hi=10.0, unit="s")
    """Simulated step time: steps take real time so the loop sees them in progress."""
    options: dict[str, Any] = setting({}, "options")
    """A hardware backend's settings, e.g. dynamixel: {port, hand} (its `from_cli` builder)."""

    def __post_init__(self) -> None:
        check_fields(self, "backend.")
        builder = getattr(BACKENDS.load(self.name), "from_cli", None)
        if builder is None:
            if self.options:
                raise ConfigError(f"backend '{self.name}' takes no options")
            return
        check_keywords(builder, {k: v for k, v in self.options.items()
                                 if k not in BACKEND_BUILDER_ARGS}, f"backend '{self.name}'")
        bad = sorted(set(self.options) & set(BACKEND_BUILDER_ARGS))
        if bad:
            raise ConfigError(f"backend.options cannot set {', '.join(bad)}: [scenario] does")
        if "cycle_budget_s" in self.options:  # refused at once, not once the bus is built
            try:
                check_cycle_budget(self.options["cycle_budget_s"])
            except HandConfigError as exc:
                raise ConfigError(f"backend.options.{exc}") from None
        hand = self.options.get("hand")
        if isinstance(hand, str):  # the loop needs the hand to know its servos
            try:
                load_hand(hand)
            except HandConfigError as exc:
                raise ConfigError(f"backend.options.hand: {quiet_hand_error(hand, exc)}"
                                  ) from None


@dataclass(frozen=True)
class ScenarioConfig:
    """Map, finger, localizer and policy: `haptic run`'s settings, with RunSettings' bounds."""

    map: str = same_as(RunSettings, "map")
    spacing: float | None = same_as(RunSettings, "spacing")
    radius: float = same_as(RunSettings, "radius")
    step: float = same_as(RunSettings, "step")
    localizer: str = same_as(RunSettings, "algorithm")
    policy: str = same_as(RunSettings, "policy")
    headings: int = same_as(RunSettings, "headings")
    max_steps: int = same_as(RunSettings, "max_steps")
    noise: bool = same_as(RunSettings, "noise")
    seed: int = same_as(RunSettings, "seed")
    start: tuple[float, float, float] | None = same_as(RunSettings, "start")
    """Simulator only: the hidden start pose; None draws one from the seed."""
    localizer_options: dict[str, Any] = same_as(RunSettings, "localizer_options")
    sensor_sigma: float | None = same_as(RunSettings, "sensor_sigma")
    """Measurement noise (m) the localizer assumes; None: from `noise`, or
    HARDWARE_SENSOR_SIGMA on a hardware backend."""
    object: str | None = setting(None, "str", optional=True)
    """A hand holding this object (`haptic run --object`: a preset NAME[:SEED] or an outline
    or mesh file) instead of a finger on `map`; None: a finger on the map."""
    hand: str | None = setting(None, "str", optional=True)
    """The hand holding `object` (`haptic run --hand`: a preset or a TOML file); None:
    two-finger."""
    plane: str | None = setting(None, "str", optional=True)
    """Where a mesh `object` is cut (`haptic run --plane`)."""
    object_units: str = setting("m", "str", choices=("m", "mm"))
    roll: float = setting(HandSettings.step, "float", lo=1e-4, hi=0.02, unit="m")
    """How far a finger of the hand rolls per step (`haptic run --roll`)."""

    def __post_init__(self) -> None:
        check_fields(self, "scenario.")
        if self.object is None:
            if self.hand is not None:
                raise ConfigError("scenario.hand names the hand that holds scenario.object: "
                                  "set object too (e.g. object = \"blob\")")
            try:
                self.run_settings()  # checks localizer_options against the localizer
            except ConfigError as exc:
                raise ConfigError(f"scenario.localizer_options: {exc}") from None
            try:  # a preset's name, or a file's spacing; no file is touched here
                check_map_spec(self.map, self.spacing)
            except MapError as exc:
                raise ConfigError(f"scenario.map: {exc}") from None
            return
        # a change merges into the running scenario: a finger's setting given earlier
        # stays unless the same change clears it (a held-out client was refused a hand
        # for options it had set long before, and not told how to go on)
        if self.start is not None:
            raise ConfigError("scenario.start places a finger on a map; an object's start "
                              "is drawn from scenario.seed: set start to nil in the same "
                              "change (changes merge into the running scenario)")
        if self.localizer_options:
            raise ConfigError("scenario.localizer_options apply to a finger on a map, not "
                              "to a hand holding an object: set localizer_options to {} in "
                              "the same change (changes merge into the running scenario)")
        try:  # a preset's name and seed, a plane and units for a file; no file is touched
            check_object_spec(self.object, plane=self.plane, units=self.object_units)
        except ObjectError as exc:
            raise ConfigError(f"scenario.object: {exc}") from None
        try:
            load_hand(self.hand_name, holding=True)
        except HandConfigError as exc:
            raise ConfigError(f"scenario.hand: "
                              f"{quiet_hand_error(self.hand_name, exc, holding=True)}"
                              ) from None
        try:
            self.hand_settings()
        except ConfigError as exc:
            raise ConfigError(f"scenario: {exc}") from None

    @property
    def hand_name(self) -> str:
        return self.hand or HandSettings.hand

    def settings(self) -> RunSettings | HandSettings:
        """A finger's settings on a map, or a hand's holding an object."""
        return self.run_settings() if self.object is None else self.hand_settings()

    def hand_settings(self) -> HandSettings:
        """`haptic run --object`'s settings (the object and hand are loaded, and checked,
        by the compute process)."""
        return HandSettings(object=self.object, plane=self.plane, units=self.object_units,
                            hand=self.hand_name, algorithm=self.localizer, seed=self.seed,
                            noise=self.noise, step=self.roll, max_steps=self.max_steps,
                            sensor_sigma=self.sensor_sigma)

    def run_settings(self) -> RunSettings:
        return RunSettings(map=self.map, spacing=self.spacing, radius=self.radius,
                           step=self.step, algorithm=self.localizer, policy=self.policy,
                           seed=self.seed, noise=self.noise, start=self.start,
                           max_steps=self.max_steps, headings=self.headings,
                           localizer_options=dict(self.localizer_options),
                           sensor_sigma=self.sensor_sigma)


@dataclass(frozen=True)
class LoopConfig:
    """The real-time loop: rate, overrun policy, stream rates. (The localizer and policy
    run in the compute process, outside the loop's ticks.)"""

    rate_hz: float = setting(200.0, "float", lo=10.0, hi=2000.0, unit="Hz")
    overrun: str = setting("skip", "str", choices=OVERRUN_POLICIES)
    """'skip': after an overrun resume at the next period boundary; 'catch_up': run late ticks."""
    cloud_hz: float = setting(4.0, "float", lo=0.1, hi=50.0, unit="Hz")
    state_every: int = setting(1, "int", lo=1, hi=100)
    """Publish `state` every N ticks."""
    cloud_points: int = setting(500, "int", lo=1, hi=20_000)
    stats_window: int = setting(1000, "int", lo=10, hi=65_536)
    """Ticks the `state` timing percentiles cover."""
    realtime_priority: int = setting(20, "int", lo=0, hi=98)
    """SCHED_FIFO priority of the loop's thread where the machine allows it (0: ordinary
    scheduling); without it a loaded machine makes ticks start late (service.daemon.priority)."""

    def __post_init__(self) -> None:
        check_fields(self, "loop.")

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.rate_hz))


@dataclass(frozen=True)
class EndpointConfig:
    pub: str = setting("tcp://127.0.0.1:5560", "str")
    cmd: str = setting("tcp://127.0.0.1:5561", "str")
    sndhwm: int = setting(1000, "int", lo=1, hi=1_000_000)
    """Messages queued per subscriber before PUB drops for that subscriber."""
    max_request_bytes: int = setting(64 * 1024, "int", lo=256, hi=MAX_FRAME_BYTES)

    def __post_init__(self) -> None:
        check_fields(self, "endpoints.")
        for name in ("pub", "cmd"):
            value = getattr(self, name)
            if "://" not in value:
                raise ConfigError(f"endpoints.{name} must be a ZeroMQ endpoint like "
                                  f"tcp://127.0.0.1:5560, got {value!r}")
            port = port_of(value)
            if port is not None and port != "*" and not (port.isdigit()
                                                         and 1 <= int(port) <= 65535):
                # ZeroMQ takes the number modulo 65536: a typed 556000 bound 31712
                what = f"port {port!r} of {value!r} is not a port" if port else (
                    f"{value!r} has no port")
                raise ConfigError(f"endpoints.{name}: {what}: give 1-65535, or * for any "
                                  "free one")
        if self.pub == self.cmd and port_of(self.pub) != "*":
            # the second bind failed as "Address already in use; is another hapticd running?"
            raise ConfigError(f"endpoints.pub and endpoints.cmd are one endpoint "
                              f"({self.pub!r}): the stream and the commands need one each")


@dataclass(frozen=True)
class SecurityConfig:
    """CurveZMQ: required for any non-loopback bind (checked by service.wire.security)."""

    curve: bool = setting(False, "bool")
    server_secret_key: str = setting("", "str")
    """Path of the server's `.key_secret` file (from `haptic keygen`)."""
    authorized_clients: str = setting("", "str")
    """Directory of client `.key` files allowed to connect (read again when it changes)."""
    serial_ports: tuple[str, ...] = setting(("/dev/ttyUSB*", "/dev/ttyACM*"), "strs")
    """Patterns of the serial ports a client's `configure` may name, besides the port this
    configuration names (`service.daemon.port_choice`)."""

    def __post_init__(self) -> None:
        check_fields(self, "security.")
        check_patterns(self.serial_ports)
        if self.curve and not (self.server_secret_key and self.authorized_clients):
            raise ConfigError("security.curve needs server_secret_key and authorized_clients")


@dataclass(frozen=True)
class LeaseConfig:
    """The controller's lease and the watchdog behind it. Bounded both ways, so no
    configuration can switch the watchdog off."""

    ttl_s: float = setting(3.0, "float", lo=0.1, hi=10.0, unit="s")
    """A controller that sends nothing for this long loses control."""
    hold_s: float = setting(1.0, "float", lo=0.0, hi=5.0, unit="s")
    """After the lease expires an active finger holds still this long, then torque goes off."""

    def __post_init__(self) -> None:
        check_fields(self, "lease.")


@dataclass(frozen=True)
class DaemonConfig:
    backend: BackendConfig = field(default_factory=BackendConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    endpoints: EndpointConfig = field(default_factory=EndpointConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    lease: LeaseConfig = field(default_factory=LeaseConfig)
    auto_configure: bool = setting(True, "bool")
    """Open the backend at start-up (state inactive) instead of waiting for `configure`."""

    def __post_init__(self) -> None:
        check_fields(self)
        if (self.scenario.object is not None and self.backend.name != "sim"
                and "hand" in self.backend.options):
            raise ConfigError("backend.options.hand names a single finger's chain; the hand "
                              "holding scenario.object is scenario.hand")
        if self.scenario.start is not None and self.backend.name != "sim":
            raise ConfigError(f"scenario.start hides the simulator's start pose; on backend "
                              f"'{self.backend.name}' the finger starts where it stands: "
                              "remove scenario.start")

    def run_settings(self) -> RunSettings | HandSettings:
        """The scenario's settings; on hardware the localizer assumes encoder-level noise."""
        settings = self.scenario.settings()
        if isinstance(settings, HandSettings):
            return hand_for_backend(settings, self.backend.name)
        return for_backend(settings, self.backend.name, self.backend.options.get("hand"))

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
            if name == "scenario":
                values = _preset_drops_spacing(values)
            parts[name] = _section(type(getattr(self, name)), name, values,
                                   base=getattr(self, name))
        scenario = parts.get("scenario")
        finger_only = sorted(set(changes.get("scenario", {})) & FINGER_ONLY)
        if scenario is not None and scenario.object is not None and finger_only:
            # stored unchecked, they would only fail (or surprise) on a switch to a finger
            raise ConfigError(f"scenario.{finger_only[0]} applies to a finger on a map, not "
                              f"to a hand holding an object; to switch to a finger, set "
                              f"object (and hand) to nil in the same change")
        return dataclasses.replace(self, **parts)


def _preset_drops_spacing(values: Any) -> Any:
    """A change of `map` to a preset, with no `spacing` of its own, drops the map file's
    spacing: kept, it refused the preset ("a spacing applies to map files"), and the way out
    (`spacing=null` beside it) was written nowhere."""
    if (isinstance(values, dict) and isinstance(values.get("map"), str)
            and "spacing" not in values
            and Path(values["map"]).suffix.lower() not in MAP_FILE_SUFFIXES):
        return {**values, "spacing": None}
    return values


SECTIONS = {f.name: f for f in dataclasses.fields(DaemonConfig)}
FINGER_ONLY = frozenset({"map", "spacing", "radius", "step", "policy", "headings"})
"""Scenario keys of a finger on a map, which a hand's scenario does not use."""


def _section(cls: type, name: str, values: Any, base: Any = None) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"[{name}] must be a table")
    known = {f.name for f in dataclasses.fields(cls)}
    for key in values:
        if (name, key) in REMOVED:
            raise ConfigError(f"{name}.{key} is gone: {REMOVED[(name, key)]}; delete it")
    unknown = sorted(str(k)[:64] for k in values if k not in known)
    if unknown:
        raise ConfigError(f"[{name}] has unknown key(s) {', '.join(unknown)}; known: "
                          f"{', '.join(sorted(known))}")
    try:  # ScenarioConfig turns a `start` list into a tuple itself
        return dataclasses.replace(base, **values) if base is not None else cls(**values)
    except TypeError as exc:
        raise ConfigError(f"[{name}]: {exc}") from None


def from_dict(data: dict[str, Any]) -> DaemonConfig:
    """A validated config from parsed TOML (or any nested dict)."""
    unknown = sorted(str(k)[:64] for k in data if k not in SECTIONS)
    if unknown:
        raise ConfigError(f"unknown config section(s) {', '.join(unknown)}; known: "
                          f"{', '.join(SECTIONS)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        if name == "auto_configure":
            kwargs[name] = value  # checked by DaemonConfig
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
    try:
        return from_dict(data)
    except ConfigError as exc:  # which file, as well as which key (a lab may keep several)
        raise ConfigError(f"{path}: {exc}") from None
