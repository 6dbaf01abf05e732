"""The daemon's core: one thread owns the backend, the loop, the explorer and both sockets.

`Node.serve()` binds the sockets, opens the backend (when `auto_configure`), then runs the
fixed-rate loop until `stop()`. Each tick reads the finger, advances exploration under the
tick's budget and publishes; requests are answered while the loop waits for its next
deadline. Because everything runs on the serving thread, no socket or backend is ever
shared between threads, and `stop()` (any thread, or a signal handler) is just an event.
"""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import sys
import threading
import time
from typing import Any

import numpy as np
import zmq
from threadpoolctl import threadpool_limits

from firmware_if.backend import Backend, FingerState
from firmware_if.errors import FirmwareError, HardwareFault
from service.daemon.config import DaemonConfig
from service.daemon.explorer import Explorer, TickOutput
from service.daemon.lifecycle import Lifecycle, State
from service.daemon.loop import RateLoop, Samples, Tick
from service.episode.scenario import RunSettings, Truth, draw_truth, episode_streams, surface_for
from service.errors import ConfigError, StateError
from service.localization.models import rotate
from service.registry import BACKENDS
from service.wire.commands import CommandServer
from service.wire.lease import Lease
from service.wire.security import CurveServer, check_binds
from service.wire.stream import Publisher

log = logging.getLogger("hapticd")
QUIET_COMMANDS = frozenset({"ping", "status", "get_config", "acquire"})
"""Commands not echoed as `command` events (they change nothing)."""


def make_backend(config: DaemonConfig, settings: RunSettings, surface: Any
                 ) -> tuple[Backend, Truth | None, Any]:
    """The configured backend (not yet opened), the sim's hidden truth, and the localizer's
    and policy's rngs.

    The seed is split by `scenario.episode_streams`, as `haptic run` splits it, so the
    first episode after configure is the episode `haptic run` runs with the same settings.
    """
    truth_rng, world_rng, loc_rng, policy_rng = episode_streams(settings.seed)
    loc_rng = (loc_rng, policy_rng)
    cls = BACKENDS.load(config.backend.name)
    if config.backend.name != "sim":
        options = dict(config.backend.options)
        factory = getattr(cls, "from_cli", None)  # the hardware backends' builder, if any
        try:
            if factory is not None:
                return factory(radius=settings.radius, step=settings.step, **options), None, \
                    loc_rng
            return cls(**options), None, loc_rng
        except TypeError as exc:
            raise ConfigError(f"backend '{config.backend.name}' options: {exc}") from None
    from sim_backend.finger import SimConfig  # concrete backend chosen at run time

    truth = draw_truth(settings, surface.map, truth_rng)
    sim = SimConfig(start=truth.as_tuple(), radius=settings.radius,
                    noise=settings.noise_spec, step_duration_s=config.backend.step_duration_s)
    return cls(surface.map, sim, world_rng), truth, loc_rng


class Node:
    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.lifecycle = Lifecycle()
        self.ready = threading.Event()
        self._stop = threading.Event()
        self._settled = False
        """Whether the first episode's long-lived objects have been frozen (`gc.freeze`)."""
        self.endpoints: dict[str, str] = {}
        self.backend: Backend | None = None
        self.truth: Truth | None = None
        """The simulator's hidden start pose as configured (None on hardware)."""
        self.episode_truth: list[float] | None = None
        """The simulator's hidden pose at the start of the current episode."""
        self.explorer: Explorer | None = None
        self.last_state: FingerState | None = None
        self.localizer_work = Samples()
        self.lease = Lease(config.lease.ttl_s)
        self.loop = RateLoop(config.loop.period_ns, self._tick, overrun=config.loop.overrun,
                             wait=self._wait)
        self.pub: Publisher | None = None
        self.cmd: CommandServer | None = None
        self._hold_until_ns: int | None = None
        self._next_cloud_ns = 0
        self._timing_cache: dict[str, Any] = {}
        self.error: BaseException | None = None
        self._curve: CurveServer | None = None
        self._revocations_seen = 0

    # -- running ---------------------------------------------------------------------------
    def serve(self) -> None:
        """Bind, configure, run the loop until `stop()`, then shut down cleanly."""
        ctx = zmq.Context()
        curve = None
        try:
            ep = self.config.endpoints
            check_binds([ep.pub, ep.cmd], self.config.security)
            if self.config.security.curve:
                curve = CurveServer(ctx, self.config.security)
                curve.start()
                self._curve = curve
            self.pub = Publisher(ctx, ep.pub, ep.sndhwm, curve)
            self.cmd = CommandServer(ctx, ep.cmd, self, self.lease,
                                     max_request_bytes=ep.max_request_bytes, curve=curve)
            self.endpoints = {"pub": self.pub.endpoint, "cmd": self.cmd.endpoint}
            _log("listening", **self.endpoints)
            if self.config.auto_configure:
                try:
                    self.configure({})
                except FirmwareError as exc:
                    _log("configure_failed", level=logging.ERROR, error=str(exc))
            self.pub.event("started", state=self.lifecycle.state.value)
            gc.collect()
            gc.freeze()  # start-up objects leave the collector's view: shorter GC pauses
            # BLAS threads buy nothing at our sizes and cost a core-handover stall (10 ms
            # when the other core is busy) in calls as small as a 20,000-vector product
            threadpool_limits(limits=1)
            self.ready.set()
            self.loop.run(self._stop.is_set)
        except BaseException as exc:
            self.error = exc
            raise
        finally:
            self._shutdown()
            if curve is not None:
                curve.stop()
            ctx.term()
            self.ready.set()

    def stop(self) -> None:
        """Ask the loop to finish (thread- and signal-safe)."""
        self._stop.set()

    def _wait(self, until_ns: int) -> None:
        """Wait for the next deadline, answering requests as they arrive."""
        while not self._stop.is_set():
            left_ms = (until_ns - time.monotonic_ns()) / 1e6
            if left_ms <= 0:
                return
            if left_ms >= 1.0:
                self.cmd.poll(timeout_ms=int(left_ms))
            else:
                time.sleep(left_ms / 1e3)

    def _tick(self, tick: Tick) -> None:
        """One tick; whatever goes wrong in it latches a fault and the loop goes on."""
        try:
            self._tick_body(tick)
        except Exception as exc:  # a bug: the daemon stays up, torque goes off
            log.exception("tick raised")
            with contextlib.suppress(Exception):
                self._fault(f"internal error in the loop: {type(exc).__name__}: {exc}")

    def _tick_body(self, tick: Tick) -> None:
        if self._curve is not None and tick.index % 50 == 0:
            self._check_revocations()
        self.pub.ensure_bound()
        ended = self.lease.expire_due()
        if ended is not None:
            self._lease_expired(*ended)
        if self._hold_until_ns is not None and tick.start_ns >= self._hold_until_ns:
            self._hold_until_ns = None
            if self.lifecycle.state is State.ACTIVE:
                self._deactivate("lease expired")
                self._event("stopped", reason="lease expired")
        state = self._read()
        loc_ns = None
        if (state is not None and self.lifecycle.state is State.ACTIVE and self.explorer
                and self.explorer.running):
            budget = tick.start_ns + int(self.config.loop.work_fraction * self.loop.period_ns)
            try:
                out = self.explorer.tick(state, self.backend.command_step, budget)
            except FirmwareError as exc:
                self._fault(f"exploration failed: {exc}")
                out = TickOutput()
            except Exception as exc:  # a localizer/policy bug: stop safely, keep serving
                log.exception("exploration raised")
                self._fault(f"internal error in exploration: {type(exc).__name__}: {exc}")
                out = TickOutput()
            loc_ns = out.localizer_ns
            self._publish_outputs(out)
        if loc_ns is not None:
            self.localizer_work.add(loc_ns)
        if tick.index % self.config.loop.state_every == 0:
            self._publish_state(tick)
        cloud = None
        if tick.start_ns >= self._next_cloud_ns and self.explorer:
            self._next_cloud_ns = tick.start_ns + int(1e9 / self.config.loop.cloud_hz)
            cloud = self.explorer.cloud()
        if cloud is not None:
            if self.explorer.estimate is not None:
                # Re-sent at the cloud's pace so late subscribers catch up with the belief.
                self.pub.publish("estimate", "estimate", self.explorer.estimate_fields())
            hyp = cloud.hypotheses  # poses, weights, total and step of one moment
            self.pub.publish("cloud", "cloud", {
                "episode": self.explorer.episode, "step": cloud.step,
                "poses": hyp.poses.astype(np.float32), "weights": hyp.weights.astype(np.float32),
                "total": cloud.total})

    def _check_revocations(self) -> None:
        """A key removed from authorized_clients: its requests are refused already; its
        subscriptions end here (every subscriber handshakes again, the revoked one fails)."""
        keyring = self._curve.keyring
        keyring.refresh()
        if keyring.revocations != self._revocations_seen:
            self._revocations_seen = keyring.revocations
            self.pub.rebind()
            _log("key_revoked", level=logging.WARNING)

    def _read(self) -> FingerState | None:
        if self.backend is None or self.lifecycle.state is State.UNCONFIGURED:
            return None
        try:
            state = self.backend.read_state()
        except FirmwareError as exc:
            self._fault(f"read failed: {exc}")  # once: in fault it only repeats
            return None
        self.last_state = state
        self.lifecycle.mark_read()
        if state.fault and self.lifecycle.state is not State.FAULT:
            self._fault(state.fault)
        return state

    # -- publishing ------------------------------------------------------------------------
    def _publish_outputs(self, out: TickOutput) -> None:
        if out.estimate_updated:
            self.pub.publish("estimate", "estimate", self.explorer.estimate_fields())
            if self.explorer.estimate.converged:
                self._next_cloud_ns = 0  # viewers get the final cloud now, not in 1/cloud_hz
        for name, fields in out.events:
            if name == "episode_started":
                self.episode_truth = self._truth_now()
                fields["truth"] = self.episode_truth
            elif name == "episode_done" and self.episode_truth is not None:
                fields["true_pose_eliminated"] = self._truth_eliminated()
            self._event(name, **fields)
            if name == "episode_done" and not self._settled:
                # the first episode loads what start-up did not (lazy imports, caches):
                # freeze that too, or every full collection scans it (12-50 ms pauses)
                self._settled = True
                gc.collect()
                gc.freeze()

    def _truth_now(self) -> list[float] | None:
        """The simulator's hidden pose where the finger is now (the start of an episode
        begun here): the configured start moved by the finger's measured displacement."""
        if self.truth is None or self.last_state is None:
            return None
        t = self.truth
        dx, dy = rotate(np.asarray(t.heading), *self.last_state.centre[:2])
        return [float(t.x + dx), float(t.y + dy), float(t.heading)]

    def _truth_eliminated(self) -> bool | None:
        """Whether a discrete localizer dropped the episode's true pose (None elsewhere)."""
        retains = getattr(self.explorer.localizer, "retains", None)
        if retains is None:
            return None
        kept = retains(tuple(self.episode_truth), 1e-6 * self.config.scenario.step, 1e-6)
        return None if kept is None else not kept

    def _publish_state(self, tick: Tick) -> None:
        if tick.index % 20 == 0 or not self._timing_cache:
            self._timing_cache = self.loop.summary(self.config.loop.stats_window)
            self._timing_cache["localizer_p99_ms"] = self.localizer_work.summary_ms(
                self.config.loop.stats_window)["p99"]
        s = self.last_state
        ex = self.explorer
        self.pub.publish("state", "state", {
            "state": self.lifecycle.state.value, "fault": self.lifecycle.fault,
            "centre": None if s is None else list(s.centre),
            "joints": [] if s is None else list(s.joints),
            "moving": bool(s and s.moving), "blocked": bool(s and s.blocked),
            "steps_done": 0 if s is None else s.steps_done,
            "torque_on": bool(s and s.torque_on),
            "exploring": bool(ex and ex.running), "phase": ex.phase.value if ex else "idle",
            "episode": ex.episode if ex else 0, "lease_holder": self.lease.holder_name,
            "timing": self._timing_cache}, t_mono_ns=tick.start_ns)

    def _event(self, name: str, **fields: Any) -> None:
        self.pub.event(name, **fields)
        _log(name, **fields)

    def on_command(self, cmd: str, client: str | None) -> None:
        if cmd not in QUIET_COMMANDS:
            self._event("command", cmd=cmd, client=client)

    # -- lifecycle -------------------------------------------------------------------------
    def _transition(self, event: str, reason: str | None = None) -> None:
        old, new = self.lifecycle.apply(event, reason)
        if old is not new:
            self._event("lifecycle", previous=old.value, state=new.value, reason=reason)

    def _fault(self, reason: str, *, again: bool = False) -> None:
        """Latch a fault: exploring stops, torque goes off as far as the backend can. A
        fault while faulted is not news (a dead port fails every read) unless `again`."""
        if self.lifecycle.state is State.FAULT and not again:
            return
        if self.explorer:
            self.explorer.stop()
        self._hold_until_ns = None
        if self.backend is not None:
            with contextlib.suppress(Exception):  # torque off is best effort on a lost bus
                self.backend.set_torque(False)
        self._transition("fault", reason)
        self._event("fault", reason=reason)

    def _deactivate(self, reason: str | None = None) -> None:
        if self.explorer:
            self.explorer.stop()
        self._hold_until_ns = None
        self.backend.set_torque(False)
        self._transition("deactivate", reason)

    def _lease_expired(self, holder: str, reason: str) -> None:
        self._event("lease_expired", client=holder, reason=reason)
        if self.lifecycle.state is State.ACTIVE:
            if self.explorer:
                self.explorer.paused = True
            self._hold_until_ns = time.monotonic_ns() + int(self.config.lease.hold_s * 1e9)
            self._event("holding", seconds=self.config.lease.hold_s)

    def _shutdown(self) -> None:
        if self.explorer:
            self.explorer.close()
        if self.backend is not None:
            with contextlib.suppress(FirmwareError):
                self.backend.set_torque(False)
            self.backend.close()
            self.backend = None
        if self.pub is not None:
            self.lifecycle.apply("shutdown")
            self._event("shutdown", state=self.lifecycle.state.value)
            self.pub.close()
        if self.cmd is not None:
            self.cmd.close()
        _log("exited")

    # -- commands (service.wire.commands.TABLE calls these) -------------------------------------
    def status(self) -> dict[str, Any]:
        ex = self.explorer
        timing = self.loop.summary()
        localizer = self.localizer_work.summary_ms()  # one percentile pass, not two
        timing["localizer_p99_ms"], timing["localizer_max_ms"] = localizer["p99"], localizer["max"]
        return {
            "state": self.lifecycle.state.value, "fault": self.lifecycle.fault,
            "exploring": bool(ex and ex.running), "phase": ex.phase.value if ex else "idle",
            "estimate": ex.estimate_fields() if ex and ex.estimate else None,
            "lease": {"holder": self.lease.holder_name,
                      "remaining_s": self.lease.remaining_s()},
            "timing": timing, "published": dict(self.pub.sent),
            "commands": {"handled": self.cmd.handled, "errors": self.cmd.errors},
            "backend": self.config.backend.name, "map": self.config.scenario.map,
            "sim_truth": self.episode_truth if self.episode_truth is not None else (
                None if self.truth is None else list(self.truth.as_tuple())),
        }

    def config_dict(self) -> dict[str, Any]:
        return self.config.to_dict()

    def configure(self, changes: dict[str, Any]) -> dict[str, Any]:
        self.lifecycle.check("configure")
        new = self.config.updated(changes)
        settings = new.run_settings()  # built and checked once
        surface = surface_for(settings)
        backend, truth, rng = make_backend(new, settings, surface)
        try:
            backend.open()
        except BaseException:
            backend.close()
            raise
        if self.backend is not None:
            self.backend.close()
        self.backend, self.truth, self.config = backend, truth, new
        episode = 1
        if self.explorer is not None:
            episode = self.explorer.episode + 1  # ids stay unique across configure
            self.explorer.close()
        self.episode_truth = None
        offload = new.loop.localizer_mode == "thread"
        self.explorer = Explorer(settings, surface, rng, offload=offload, first_episode=episode,
                                 cloud_points=new.loop.cloud_points)
        if offload:  # let the loop thread take the GIL back from the worker promptly
            sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        self.last_state = None
        self.lease.ttl_ns = int(new.lease.ttl_s * 1e9)
        if new.loop.period_ns != self.loop.period_ns or new.loop.overrun != self.loop.overrun:
            self.loop.overrun = new.loop.overrun
            self.loop.retime(new.loop.period_ns)
        self._transition("configure")
        return {"state": self.lifecycle.state.value}

    def activate(self) -> dict[str, Any]:
        self.lifecycle.check("activate")
        self.lifecycle.require_valid_read()
        try:
            self.backend.set_torque(True)
        except HardwareFault as exc:  # e.g. the bus went away while touching down
            self._fault(f"activate failed: {exc}")
            raise
        self._transition("activate")
        return {"state": self.lifecycle.state.value}

    def deactivate(self) -> dict[str, Any]:
        self.lifecycle.check("deactivate")
        self._deactivate()
        return {"state": self.lifecycle.state.value}

    def start_exploration(self, repeat: bool) -> dict[str, Any]:
        if self.lifecycle.state is not State.ACTIVE:
            raise StateError(f"cannot start exploration while {self.lifecycle.state.value}; "
                             f"activate first")
        if self.explorer.running:
            raise StateError("already exploring; stop_exploration first")
        if self._hold_until_ns is not None:
            raise StateError("the finger is holding after a lost lease and will stop")
        state = self.last_state
        if state is None or state.moving:
            raise StateError("a step is still under way; try again in a moment")
        self._publish_outputs(self.explorer.start(state, repeat))
        return {"episode": self.explorer.episode,
                "candidates": self.explorer.estimate.candidates}

    def stop_exploration(self) -> dict[str, Any]:
        was = bool(self.explorer and self.explorer.running)
        if self.explorer:
            self.explorer.stop()
        self._hold_until_ns = None
        return {"was_exploring": was}

    def reset(self) -> dict[str, Any]:
        """Clear the fault: the backend re-opens its port and configures every servo again;
        if that fails the daemon stays in fault and the reply says why."""
        self.lifecycle.check("reset")
        self.backend.clear_fault()
        self.last_state = None
        self._transition("reset")
        return {"state": self.lifecycle.state.value}

    def estop(self, reason: str) -> dict[str, Any]:
        if self.lifecycle.state is not State.UNCONFIGURED:
            self._fault(f"estop: {reason}", again=True)
        return {"state": self.lifecycle.state.value}

    def reset_stats(self) -> dict[str, Any]:
        self.loop.reset_stats()
        self.localizer_work.reset()
        return {}


def _log(event: str, level: int = logging.INFO, **fields: Any) -> None:
    """One structured log record; the daemon's formatter prints it as a JSON line."""
    log.log(level, event, extra={"fields": fields})


def json_line(record: logging.LogRecord) -> str:
    out = {"t": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)),
           "level": record.levelname.lower(), "event": record.getMessage()}
    out.update(getattr(record, "fields", {}) or {})
    return json.dumps(out, default=str)

