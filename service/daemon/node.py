"""The daemon's core: one thread owns the backend, the loop, the explorer and both sockets.

`Node.serve()` binds the sockets, starts the compute process (`service.daemon.worker`,
where maps, localizers and policies live) and configures (when `auto_configure`), then
runs the fixed-rate loop until `stop()`. Each tick reads the hand (every finger, one
`read_hand`; a single finger is a hand of one), takes in the compute process's replies,
advances exploration and publishes; requests are answered while the loop waits for its
next deadline. Slow work never runs in a tick: it is in the compute
process, or (opening a new backend) on a helper thread while the loop leaves the backend
be. `stop()` (any thread, or a signal handler) is just an event. The command handlers are
in `service.daemon.controls`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import logging
import threading
import time
from typing import Any

import numpy as np
import zmq
from threadpoolctl import threadpool_limits

from firmware_if.backend import Backend, HandState
from firmware_if.errors import FirmwareError
from service.daemon.config import DaemonConfig
from service.daemon.controls import CommandHandlers
from service.daemon.explorer import Explorer, TickOutput
from service.daemon.lifecycle import Lifecycle, State
from service.daemon.loop import RateLoop, Samples, Tick
from service.daemon.priority import Scheduling, set_loop_priority
from service.daemon.reconfigure import Reconfiguration, Stage
from service.daemon.reset_job import Reset
from service.daemon.worker_link import WorkerDied, WorkerLink
from service.episode.scenario import Truth
from service.errors import StateError
from service.localization.models import rotate
from service.wire.commands import CommandServer, Deferred
from service.wire.envelope import Message
from service.wire.lease import Lease
from service.wire.security import CurveServer, check_binds
from service.wire.stream import Publisher

log = logging.getLogger("hapticd")

ANSWER_SHARE = 0.25
"""Share of each period the loop thread may spend answering requests; the rest wait for
the next tick (a request costs 0.1-1 ms: a few hundred a second fit at any rate)."""


class Node(CommandHandlers):
    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.operator_ports = frozenset(
            p for p in [config.backend.options.get("port")] if isinstance(p, str))
        """The port hapticd's own configuration names: a client may always go back to it
        (`port_choice`)."""
        self.lifecycle = Lifecycle()
        self.ready = threading.Event()
        """Set once serving and the start-up configure has finished (or failed)."""
        self._stopping = False
        """Set by `stop`: a plain flag, not a threading.Event, whose lock a signal handler
        may not take (two SIGTERMs at once, as `pkill -f` sends to `timeout` and to us: the
        second handler ran inside the first's Event.set and waited on its lock for ever)."""
        self._settled = False
        """Whether the first episode's long-lived objects have been frozen (`gc.freeze`)."""
        self.endpoints: dict[str, str] = {}
        self.backend: Backend | None = None
        self.truth: Truth | None = None
        """The simulator's hidden start pose as configured (None on hardware)."""
        self.episode_truth: list[float] | None = None
        """The simulator's hidden pose at the start of the current episode."""
        self.explorer: Explorer | None = None
        self.link = WorkerLink()
        self.reconf: Reconfiguration | None = None
        self.resetting: Reset | None = None
        """A `reset` at work on the bus beside the loop (`reset_job`)."""
        self.starting: Deferred | None = None
        """A `start_exploration` waiting for the episode's first belief."""
        self.faults = 0
        self.configure_error: str | None = None
        """Why the last configure failed (the one at start-up too), until one succeeds."""
        self.map_warnings: list[str] = []
        """The map check's warnings on the configured map (`status`)."""
        self.last_state: HandState | None = None
        self.localizer_work = Samples()
        self.lease = Lease(config.lease.ttl_s)
        self.loop = RateLoop(config.loop.period_ns, self._tick, overrun=config.loop.overrun,
                             wait=self._wait)
        self.pub: Publisher | None = None
        self.cmd: CommandServer | None = None
        self._hold_until_ns: int | None = None
        self._fault_to_tell: tuple[str, dict[str, Any] | None] | None = None
        """A fault's reason and the episode it cut, held back while the bus asks its servos
        why (`_tell_fault`)."""
        self._next_cloud_ns = 0
        self._timing_cache: dict[str, Any] = {}
        self.error: BaseException | None = None
        self._curve: CurveServer | None = None
        self._revocations_seen = 0
        self.scheduling: Scheduling | None = None
        """What the loop's thread runs under (set as the loop starts)."""

    # -- running ---------------------------------------------------------------------------
    def serve(self) -> None:
        """Bind, start the compute process, configure, run the loop until `stop()`, then
        shut down cleanly."""
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
            self.link.start()
            _preload()
            if self.config.auto_configure:
                self.configure({}).on_settle(self._configured_at_start)
            else:
                self.ready.set()
            self.pub.event("started", state=self.lifecycle.state.value)
            gc.collect()
            gc.freeze()  # start-up objects leave the collector's view: shorter GC pauses
            # BLAS threads buy nothing at our sizes and cost a core-handover stall (10 ms
            # when the other core is busy) in calls as small as a 20,000-vector product
            threadpool_limits(limits=1)
            self._apply_priority()
            self.loop.run(self._stopped)
        except BaseException as exc:
            self.error = exc
            raise
        finally:
            self._shutdown()
            if curve is not None:
                curve.stop()
            ctx.term()
            self.ready.set()

    def _apply_priority(self) -> None:
        """The loop's thread under real-time scheduling as configured, or a warning why not."""
        before, self.scheduling = self.scheduling, set_loop_priority(
            self.config.loop.realtime_priority)
        if self.scheduling == before:
            return
        _log("loop_scheduling", level=logging.WARNING if self.scheduling.note else logging.INFO,
             **dataclasses.asdict(self.scheduling))

    def _configured_at_start(self, result: dict[str, Any] | None, error: Exception | None
                             ) -> None:
        if isinstance(error, ShuttingDown):  # stopped before it was done: no failure
            _log("configure_abandoned", error=str(error))
        elif error is not None:
            self.configure_error = str(error)
            _log("configure_failed", level=logging.ERROR, error=str(error))
        self.ready.set()

    def stop(self) -> None:
        """Ask the loop to finish (from any thread, or a signal handler: it takes no lock)."""
        self._stopping = True

    def _stopped(self) -> bool:
        return self._stopping

    def _wait(self, until_ns: int) -> None:
        """Wait for the next deadline, answering requests as they arrive, for at most
        `ANSWER_SHARE` of the period each tick. Anyone may send requests: a flood of them
        (an observer's `status` as fast as it could) kept this thread, at its real-time
        priority, busy the whole period, and the bus's replies starved (a fault in 0.2 s).
        Under a whole millisecond left, the socket is looked at without waiting: a loop past
        950 Hz never had one, and answered nothing."""
        left_to_answer = int(self.loop.period_ns * ANSWER_SHARE)
        while not self._stopping:
            now = time.monotonic_ns()
            if now >= until_ns:
                return
            if left_to_answer <= 0 or until_ns - now < 1_000_000:
                if left_to_answer > 0:
                    left_to_answer -= self._answer(min(until_ns, now + left_to_answer))
                time.sleep(max(until_ns - time.monotonic_ns(), 0) / 1e9)
                return
            if self.cmd.wait(timeout_ms=(until_ns - now) // 1_000_000):
                left_to_answer -= self._answer(min(until_ns, time.monotonic_ns()
                                                   + left_to_answer))

    def _answer(self, until_ns: int) -> int:
        """Answer the waiting requests until `until_ns`; the time it took (ns)."""
        start = time.monotonic_ns()
        self.cmd.answer(until_ns)
        return time.monotonic_ns() - start

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
        replies = self._worker_replies()
        ended = self.lease.expire_due()
        if ended is not None:
            self._lease_expired(*ended)
        if self._hold_until_ns is not None and tick.start_ns >= self._hold_until_ns:
            self._hold_until_ns = None
            if self.lifecycle.state is State.ACTIVE:
                self._deactivate("lease expired")
                self._event("stopped", reason="lease expired")
        if self.resetting is not None and self.resetting.done:
            self._end_reset()  # before the read: the hand read at once after it
        state = self._read()
        self._tell_fault()
        if self.reconf is not None:
            self._reconfigure(replies)
        if (state is not None and self.lifecycle.state is State.ACTIVE and self.explorer
                and self.explorer.running):
            self._explore(state, replies)
        if tick.index % self.config.loop.state_every == 0:
            self._publish_state(tick)
        if tick.start_ns >= self._next_cloud_ns and self.explorer:
            self._next_cloud_ns = tick.start_ns + int(1e9 / self.config.loop.cloud_hz)
            self._publish_cloud()

    def _worker_replies(self) -> list[Message]:
        try:
            return self.link.poll()
        except WorkerDied as exc:
            self._compute_died(exc)
            return []

    def _compute_died(self, exc: WorkerDied) -> None:
        """Whatever waited for the compute process fails; a new one starts at once."""
        _log("compute_process_died", level=logging.ERROR, error=str(exc))
        if self.reconf is not None:
            self._end_reconfigure(exc)
        if self.explorer is not None and self.explorer.running:
            self._fault(f"the localizer's process died: {exc}")
        self._fail_start(exc)
        self.link.start()

    def _explore(self, state: HandState, replies: list[Message]) -> None:
        try:
            out = self.explorer.tick(state, self.backend.command_hand, replies)
        except WorkerDied as exc:  # a request found it gone before a poll did
            self._compute_died(exc)
            return
        except FirmwareError as exc:
            self._fault(f"exploration failed: {exc}")
            self._fail_start(exc)
            return
        except Exception as exc:  # a localizer/policy error: stop safely, keep serving
            log.exception("exploration raised")
            self._fault(f"error in exploration: {type(exc).__name__}: {exc}")
            self._fail_start(exc)
            return
        if out.localizer_ms is not None:
            self.localizer_work.add(int(out.localizer_ms * 1e6))
        self._publish_outputs(out)

    def _fail_start(self, error: Exception) -> None:
        if self.starting is not None:
            self.starting.fail(error)
            self.starting = None

    def _reconfigure(self, replies: list[Message]) -> None:
        """Advance the configure under way; commit it once every part has worked."""
        rc = self.reconf
        stage = rc.step(replies)
        if stage is Stage.FAILED:
            if rc.reopen_error is not None:  # else the next read says only "not open"
                self._fault(f"the bus did not open again after the configure failed: "
                            f"{rc.reopen_error}; once the bus answers, send reset or "
                            "configure")
            self._end_reconfigure(rc.error)
        elif stage is Stage.READY:
            if self.faults != rc.fault_count:
                self._end_reconfigure(StateError(
                    "a fault was latched (an estop?) while configuring; nothing was changed: "
                    "configure again or reset"))
            else:
                self._commit(rc)

    def _end_reconfigure(self, error: Exception) -> None:
        # the requester is told in its reply, and a refused request changes nothing, so
        # `configure_error` keeps the start-up's (`_configured_at_start`), which no one asked
        rc, self.reconf = self.reconf, None
        rc.abandon()
        rc.deferred.fail(error)

    def _check_revocations(self) -> None:
        """A key removed from authorized_clients: its requests are refused already; its
        subscriptions end here (every subscriber handshakes again, the revoked one fails)."""
        keyring = self._curve.keyring
        keyring.refresh()
        if keyring.revocations != self._revocations_seen:
            self._revocations_seen = keyring.revocations
            self.pub.rebind()
            _log("key_revoked", level=logging.WARNING, keys=list(keyring.revoked))

    @property
    def _bus_elsewhere(self) -> bool:
        """Another thread works on the bus, and the loop leaves it be: a new backend opening,
        perhaps on the same bus (`reconfigure`), or a reset (`reset_job`)."""
        return bool(self.reconf is not None and self.reconf.opening
                    or self.resetting is not None)

    def _read(self) -> HandState | None:
        if self.backend is None or self.lifecycle.state is State.UNCONFIGURED:
            return None
        if self._bus_elsewhere:
            return None
        try:
            state = self.backend.read_hand()  # every finger, in one bus read
        except FirmwareError as exc:
            self._fault(f"read failed: {exc}")  # once: in fault it only repeats
            return None
        self.last_state = state
        self.lifecycle.mark_read()
        fault = next((f.fault for f in state.fingers if f.fault), None)
        if fault and self.lifecycle.state is not State.FAULT:
            self._fault(fault)
        return state

    # -- publishing ------------------------------------------------------------------------
    def _publish_outputs(self, out: TickOutput) -> None:
        if out.estimate_updated:
            self.pub.publish("estimate", "estimate", self.explorer.estimate_fields())
            if self.explorer.estimate["converged"]:
                self._next_cloud_ns = 0  # viewers get the final cloud now, not in 1/cloud_hz
        if out.started and self.starting is not None:
            self.starting.resolve({"episode": self.explorer.episode,
                                   "candidates": self.explorer.candidates})
            self.starting = None
        for name, fields in out.events:
            if name == "episode_started":
                self.episode_truth = fields["truth"]
            self._event(name, **fields)
            if name == "episode_done" and not self._settled:
                # the first episode loads what start-up did not (lazy imports, caches):
                # freeze that too, or every full collection scans it (12-50 ms pauses)
                self._settled = True
                gc.collect()
                gc.freeze()

    def truth_at(self, state: HandState) -> list[float] | None:
        """The simulator's hidden pose now (the start of an episode begun here): a finger's
        own (`SimulatedFinger.pose`), else the configured start moved by its measured
        displacement; a hand's, the object's."""
        if self.truth is None:
            return None
        if self.explorer is not None and self.explorer.kind == "hand":
            return self.hidden().get("truth")
        pose = getattr(self.backend, "pose", None)
        if pose is not None:
            return [float(v) for v in pose]
        t = self.truth
        dx, dy = rotate(np.asarray(t.heading), *state.fingers[0].centre[:2])
        return [float(t.x + dx), float(t.y + dy), float(t.heading)]

    def hidden(self) -> dict[str, Any]:
        """The simulated hand's hidden state now, for the record: the object's pose and the
        grasp's true quality, now and its least during the last move (nothing for a finger
        or on hardware)."""
        quality = getattr(self.backend, "quality", None)  # only the simulated hand has it
        if self.truth is None or quality is None:
            return {}
        return {"truth": [float(v) for v in self.backend.pose], "quality": float(quality),
                "least_quality": float(self.backend.step_min_quality)}

    def _publish_state(self, tick: Tick) -> None:
        if tick.index % 20 == 0 or not self._timing_cache:
            self._timing_cache = self.loop.summary(self.config.loop.stats_window)
            self._timing_cache["localizer_p99_ms"] = self.localizer_work.summary_ms(
                self.config.loop.stats_window)["p99"]
        s = self.last_state
        self.pub.publish("state", "state", {
            **self._lifecycle_fields(),
            "fingers": [] if s is None else [
                {"name": name, "centre": list(f.centre), "joints": list(f.joints),
                 "moving": f.moving, "blocked": f.blocked}
                for name, f in zip(self._finger_names(len(s.fingers)), s.fingers,
                                   strict=True)],
            "moving": bool(s and s.moving), "dropped": bool(s and s.dropped),
            "steps_done": 0 if s is None else s.fingers[0].steps_done,
            "lease_holder": self.lease.holder_name,
            "timing": self._timing_cache}, t_mono_ns=tick.start_ns)

    def _finger_names(self, count: int) -> tuple[str | None, ...]:
        """The backend's names of its `count` fingers (None where it has none to give: the
        last state read outlives a backend that failed to open again)."""
        names = () if self.backend is None else self.backend.finger_names()
        return names if len(names) == count else (None,) * count

    def _lifecycle_fields(self) -> dict[str, Any]:
        """What the stream's `state` and the `status` reply both say of the lifecycle and
        the episode: one home, so the two never disagree."""
        s, ex = self.last_state, self.explorer
        return {"state": self.lifecycle.state.value, "fault": self.lifecycle.fault,
                "exploring": bool(ex and ex.running),
                "phase": ex.phase.value if ex else "idle", "episode": ex.episode if ex else 0,
                "torque_on": bool(s and s.fingers[0].torque_on)}

    def _publish_cloud(self) -> None:
        cloud = self.explorer.cloud()
        if cloud is None:
            return
        if self.explorer.estimate is not None:
            # Re-sent at the cloud's pace so late subscribers catch up with the belief.
            self.pub.publish("estimate", "estimate", self.explorer.estimate_fields())
        hyp = cloud.hypotheses  # poses, weights, total and step of one moment
        self.pub.publish("cloud", "cloud", {
            "episode": self.explorer.episode, "step": cloud.step,
            "poses": hyp.poses, "weights": hyp.weights, "total": cloud.total})

    def _event(self, name: str, **fields: Any) -> None:
        self.pub.event(name, **fields)
        _log(name, _event_level(name, fields), **fields)

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
        self.faults += 1
        cut = self.explorer.stop("fault") if self.explorer else None
        self._fail_start(StateError(f"faulted: {reason}"))
        self._hold_until_ns = None
        if self.backend is not None and not self._bus_elsewhere:
            # (a reset leaves torque off, and one this fault voids sends it once it is done)
            with contextlib.suppress(Exception):  # torque off is best effort on a lost bus
                self.backend.set_torque(False)
        self._transition("fault", reason)
        if not again and getattr(self.backend, "diagnosing", False):
            self._fault_to_tell = (reason, cut)  # its words are still coming
        else:
            self._event("fault", reason=reason)
            self._episode_cut(cut)

    def _tell_fault(self, *, wait: bool = False) -> None:
        """Publish the `fault` event, and the end of the episode it cut, held back while
        the bus asked its servos why its cycles failed (on a thread of its own: the loop
        goes on): with the words that found, once found (`wait`: now)."""
        if self._fault_to_tell is None or not wait and getattr(self.backend, "diagnosing",
                                                               False):
            return
        (reason, cut), self._fault_to_tell = self._fault_to_tell, None
        told = reason if self.backend is None else self.backend.with_diagnosis(reason)
        if self.lifecycle.fault:
            self.lifecycle.fault = self.lifecycle.fault.replace(reason, told, 1)
        self._event("fault", reason=told)
        self._episode_cut(cut)

    def _deactivate(self, reason: str | None = None) -> None:
        cut = self.explorer.stop("deactivated") if self.explorer else None
        self._fail_start(StateError("deactivated before the first belief"))
        self._hold_until_ns = None
        self.backend.set_torque(False)
        self._read_now()
        self._transition("deactivate", reason)
        self._episode_cut(cut)

    def _read_now(self) -> None:
        """Read the hand at once, so that a command's reply, and a `status` asked right
        after it, tell what it did (a held-out client read torque on from `status` just
        after `deactivate` answered, in 4 of 5 tries: the last read was from before). A
        read that fails here fails again at the next tick, which latches it."""
        with contextlib.suppress(Exception):
            self.last_state = self.backend.read_hand()

    def _episode_cut(self, cut: dict[str, Any] | None) -> None:
        """An episode cut short still ends with `episode_done`: a client or a recording
        knows it is over, and with what estimate."""
        if cut is not None:
            self._event("episode_done", **cut)

    def _lease_expired(self, holder: str, reason: str) -> None:
        self._event("lease_expired", client=holder, reason=reason)
        if self.lifecycle.state is State.ACTIVE:
            if self.explorer:
                self.explorer.paused = True
            self._hold_until_ns = time.monotonic_ns() + int(self.config.lease.hold_s * 1e9)
            self._event("holding", seconds=self.config.lease.hold_s)

    def _shutdown(self) -> None:
        """Exploring stops, torque goes off and the backend closes; subscribers hear the
        episode end (`episode_done`, reason `shutdown`), the last `state` (torque off) and
        `shutdown`, in that order (a helper's client waited for an `episode_done` that
        never came, and the last `state` it saw had torque on). A request under way is
        answered (a held-out client's `configure` and `start_exploration` got no reply)."""
        if self.reconf is not None:
            self._end_reconfigure(_shutting_down("the configure ended with it, nothing was "
                                                 "changed"))
        if self.resetting is not None:  # the bus is the reset's until it is done
            self.resetting.wait()
            self.resetting.deferred.fail(_shutting_down("the reset ended with it, torque "
                                                        "off"))
            self.resetting = None
        self._fail_start(_shutting_down("the episode ended before its first belief"))
        self._tell_fault(wait=True)
        cut = self.explorer.stop("shutdown") if self.explorer else None
        if self.backend is not None:
            with contextlib.suppress(Exception):
                self.backend.set_torque(False)
            self._read_now()  # the last state: torque off
            with contextlib.suppress(Exception):
                self.backend.close()
        self.link.close()
        if self.pub is not None:
            self._episode_cut(cut)
            self.lifecycle.apply("shutdown")
            now = time.monotonic_ns()
            with contextlib.suppress(Exception):  # `shutdown` goes out whatever happens
                # the closed backend still names its fingers (a held-out client saw them
                # nil in the last state, the backend dropped before it was published)
                self._publish_state(Tick(index=0, start_ns=now, due_ns=now, deadline_ns=now))
            self._event("shutdown", state=self.lifecycle.state.value)
            self.pub.close()
        self.backend = None
        served = self.pub is not None or self.cmd is not None
        if self.cmd is not None:
            self.cmd.close()
        if served:  # a start refused before binding is its one error line, nothing more
            _log("exited")


def _preload() -> None:
    """Import every localizer, policy and backend now: `configure` checks options against
    their signatures, and an import inside a command would stall the loop for a second."""
    from service.registry import BACKENDS, LOCALIZERS, POLICIES

    for registry in (LOCALIZERS, POLICIES, BACKENDS):
        for name in registry.names():
            with contextlib.suppress(ImportError):  # a backend this machine lacks
                registry.load(name)


def _event_level(name: str, fields: dict[str, Any]) -> int:
    """An event's log level: a fault (and the lifecycle entering one) an error, a lease lost
    and the torque it turns off a warning, the rest info. A lab that runs with `--log-level
    warning` to keep the steps out of its log must still find its faults there."""
    if name == "fault" or (name == "lifecycle" and fields.get("state") == "fault"):
        return logging.ERROR
    if name in ("lease_expired", "stopped"):
        return logging.WARNING
    return logging.INFO


def _log(event: str, level: int = logging.INFO, **fields: Any) -> None:
    """One structured log record; the daemon's formatter prints it as a JSON line."""
    log.log(level, event, extra={"fields": fields})


class ShuttingDown(StateError):
    """The reply to a request a shutdown cut short."""


def _shutting_down(what: str) -> ShuttingDown:
    return ShuttingDown(f"hapticd is shutting down: {what}; start hapticd again")
