"""A `configure` in progress, off the loop: nothing is replaced until all of it has worked.

The new config was validated whole before a Reconfiguration starts. Then the compute
process loads the map, builds the surface, checks the localizer and, for the simulator,
builds the world (`setup`); when it is ready, a helper thread builds and opens the new
backend (bus I/O, or mapping the simulated world's arrays). Only then does the loop commit:
swap the backend, tell the compute process, apply the loop and lease settings. If any part
fails the old backend, config and scenario stay as they were.

The backend is rebuilt only when it must be: a new backend section, the simulator (its
world follows the map and seed), or a daemon without a working one (unconfigured, fault).
"""

from __future__ import annotations

import contextlib
import inspect
import json
import threading
from dataclasses import asdict
from enum import StrEnum
from typing import Any

import numpy as np

from firmware_if.backend import Backend
from firmware_if.errors import HandConfigError, HardwareFault
from service.bounds import keyword_params
from service.daemon.config import BACKEND_BUILDER_ARGS, DaemonConfig
from service.daemon.quiet_files import quiet_hand_error
from service.daemon.worker_link import WorkerLink
from service.episode.hand_scenario import HandSettings
from service.episode.scenario import RunSettings, Truth
from service.errors import ConfigError, ServiceError
from service.registry import BACKENDS
from service.wire.commands import Deferred
from service.wire.envelope import Message


class Stage(StrEnum):
    SETUP = "setup"
    """The compute process prepares the scenario."""
    OPENING = "opening"
    """A helper thread opens the new backend."""
    READY = "ready"
    FAILED = "failed"


class Reconfiguration:
    def __init__(self, new: DaemonConfig, settings: RunSettings, link: WorkerLink,
                 deferred: Deferred, *, rebuild_backend: bool, fault_count: int,
                 release: Backend | None = None, recover: bool = False) -> None:
        self.new = new
        self.recover = recover
        """Configured in fault: a servo's hardware error is cleared as `reset` does (the
        servo rebooted, named in `rebooted`), not a reason to fail."""
        self.rebooted: list[str] = []
        self.release = release
        """The old backend, when the new one opens its port: a serial port opens once, so
        the old one lets it go first, and opens it again if the new one fails."""
        self.settings = settings
        self.link = link
        self.deferred = deferred
        self.rebuild_backend = rebuild_backend
        self.fault_count = fault_count
        """Faults latched before this began: one latched since (an estop) voids it."""
        self.stage = Stage.SETUP
        self.error: Exception | None = None
        self.backend: Backend | None = None
        self.truth: Truth | None = None
        self._world: dict[str, Any] | None = None
        self.warnings: list[str] = []
        """The map check's warnings on the new scenario's map."""
        self._thread: threading.Thread | None = None
        self.reopen_error: Exception | None = None
        """Why the old backend, released for the new one, did not open again after the new
        one failed: the daemon is left without a bus, a fault it must name."""
        self.req = link.send("setup", settings=asdict(settings), backend=new.backend.name,
                             scenario="hand" if isinstance(settings, HandSettings) else "finger",
                             cloud_points=new.loop.cloud_points)

    @property
    def opening(self) -> bool:
        """The helper thread may be talking to the bus: the loop leaves the backend be."""
        return self.stage is Stage.OPENING

    def step(self, replies: list[Message]) -> Stage:
        """Advance with this tick's replies from the compute process."""
        for msg in replies:
            if int(msg.get("req", -1)) != self.req or self.stage is not Stage.SETUP:
                continue
            if msg.type == "error":
                self._fail(_ComputeRefusal(str(msg.get("code")), str(msg.get("message"))))
            elif msg.type == "ready":
                truth = msg.get("truth")
                self.truth = None if truth is None else Truth(*truth)
                self._world = msg.get("world")
                self.warnings = [str(w) for w in msg.get("warnings") or []]
                if self.rebuild_backend:
                    self.stage = Stage.OPENING
                    self._thread = threading.Thread(target=self._open, daemon=True,
                                                    name="hapticd-configure")
                    self._thread.start()
                else:
                    self.stage = Stage.READY
        if self.stage is Stage.OPENING and not self._thread.is_alive():
            self.stage = Stage.FAILED if self.error is not None else Stage.READY
        return self.stage

    def _open(self) -> None:
        """Helper thread: build and open the new backend (I/O waits release the GIL)."""
        if self.release is not None:
            with contextlib.suppress(Exception):  # torque off, port released
                self.release.close()
        try:
            backend = make_backend(self.new, self.settings, self.truth, self._world)
            try:
                try:
                    backend.open()
                except HardwareFault:
                    if not self.recover:
                        raise
                    self.rebooted = backend.clear_fault()  # as reset does
            except BaseException:
                with contextlib.suppress(Exception):
                    backend.close()
                raise
            self.backend = backend
        except Exception as exc:  # reported to the client; the old backend stays
            self.error = exc
            if self.release is not None:
                try:
                    self.release.open()
                except Exception as again:  # the daemon latches it as a fault, named
                    self.reopen_error = again

    def _fail(self, error: Exception) -> None:
        self.error = error
        self.stage = Stage.FAILED

    def abandon(self) -> None:
        """Drop what was prepared (after a failure, or a fault that voids it)."""
        with contextlib.suppress(Exception):
            self.link.send("discard")
        if self._thread is not None:
            self._thread.join(10)
        if self.backend is not None:
            with contextlib.suppress(Exception):
                self.backend.close()
            self.backend = None


class _ComputeRefusal(ServiceError):
    """The compute process refused the setup (a map, a localizer option: `bad_config`) or
    failed it (`internal`)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def check_backend_options(config: DaemonConfig, settings: RunSettings | HandSettings
                          ) -> None:
    """Refuse backend options that lack a keyword the backend's builder needs, naming it:
    checked with the rest of a configure, before the scenario is prepared (a held-out lab
    waited 1.3-9 s on a map it had not changed for this refusal)."""
    if config.backend.name == "sim":
        return
    if isinstance(settings, HandSettings):
        from firmware_if.dynamixel_hand import DynamixelHand

        _check_required(config.backend.name, DynamixelHand.from_cli, config.backend.options,
                        ("hand",), '{"port": "/dev/ttyUSB0"}')
        return
    factory = getattr(BACKENDS.load(config.backend.name), "from_cli", None)
    if factory is not None:  # the hardware backends' builder, if any
        _check_required(config.backend.name, factory, config.backend.options,
                        BACKEND_BUILDER_ARGS, '{"port": "/dev/ttyUSB0", "hand": "planar"}')


def make_backend(config: DaemonConfig, settings: RunSettings | HandSettings,
                 truth: Truth | None, world: dict[str, Any] | None) -> Backend:
    """The configured backend, not yet opened. The simulator's world (the perturbed map
    and its contact surface) was built by the compute process and is mapped here. Its
    options were checked with the rest of the configure (`check_backend_options`)."""
    if isinstance(settings, HandSettings):
        return _hand_backend(config, settings)
    cls = BACKENDS.load(config.backend.name)
    if config.backend.name != "sim":
        options = dict(config.backend.options)
        factory = getattr(cls, "from_cli", None)
        try:
            if factory is not None:
                return _beside_the_loop(factory(radius=settings.radius, step=settings.step,
                                                **options))
            return _beside_the_loop(cls(**options))
        except HandConfigError as exc:  # a hand file's content is not the client's business
            raise quiet_hand_error(str(options.get("hand", "")), exc) from None
        except TypeError as exc:
            raise ConfigError(f"backend '{config.backend.name}' options: {exc}") from None
    from service.localization.surface import ContactSurface, HeightMap
    from sim_backend.finger import SimConfig

    heights = np.load(world["paths"]["heights"], mmap_mode="r", allow_pickle=False)
    centre = np.load(world["paths"]["centre"], mmap_mode="r", allow_pickle=False)
    world_map = HeightMap(heights, world["spacing"], name=world["name"])
    surface = ContactSurface(map=world_map, radius=settings.radius, centre_heights=centre)
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = json.loads(world["rng"])
    sim = SimConfig(start=truth.as_tuple(), radius=settings.radius,
                    noise=settings.noise_spec, step_duration_s=config.backend.step_duration_s)
    return cls(world_map, sim, rng, surface=surface)


def _hand_backend(config: DaemonConfig, settings: HandSettings) -> Backend:
    """A hand holding the object: the seed's simulated hand (as `haptic run --object` runs
    it) or `scenario.hand` on Dynamixel servos (as `haptic run --object --backend
    dynamixel`)."""
    if config.backend.name == "sim":
        from service.episode.hand_episode import simulated_hand
        from service.episode.hand_scenario import load_parts

        return simulated_hand(settings, load_parts(settings),
                              step_duration_s=config.backend.step_duration_s)[0]
    from firmware_if.dynamixel_hand import DynamixelHand

    try:
        return _beside_the_loop(DynamixelHand.from_cli(hand=settings.hand,
                                                       **config.backend.options))
    except TypeError as exc:
        raise ConfigError(f"backend '{config.backend.name}' options for a hand: {exc}") from None


def _beside_the_loop(backend: Backend) -> Backend:
    """A daemon's servo bus asks its servos why its cycles failed on a thread of its own
    (`DxlBus.diagnose_in_background`): in the tick that latched the fault, the control
    loop stopped for 0.7-1 s, its state stream and every reply with it."""
    bus = getattr(backend, "bus", None)
    if bus is not None:
        bus.diagnose_in_background = True
    return backend


def _check_required(name: str, factory: Any, options: dict[str, Any],
                    supplied: tuple[str, ...], example: str) -> None:
    """Refuse `options` that lack one of `factory`'s required keywords (beside those the
    daemon `supplied`), naming it: Python's own words ("from_cli() missing 1 required
    keyword-only argument") told a client nothing it could act on."""
    missing = [key for key, (_, default) in keyword_params(factory).items()
               if default is inspect.Parameter.empty and key not in options
               and key not in supplied]
    if missing:
        raise ConfigError(
            f"backend.options for '{name}' need {', '.join(missing)} beside what they give "
            f"({', '.join(options) or 'nothing'}): a configure replaces the whole table, "
            f"e.g. backend.options={example}")
