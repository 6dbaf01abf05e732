"""The node's command handlers (service.wire.commands.TABLE calls these), on the loop thread.

Each either answers at once or returns a `Deferred` for work that happens off the loop:
`configure` (and `set_map`, `set_localizer`, `set_policy`) waits for the compute process
and a new backend; `reset` for the bus (`reset_job`); `start_exploration` waits for the
episode's first belief. A refused
request changes nothing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
from typing import TYPE_CHECKING, Any

from firmware_if.errors import HardwareFault
from service.daemon.explorer import Explorer
from service.daemon.lifecycle import State
from service.daemon.port_choice import chosen_port
from service.daemon.reconfigure import Reconfiguration, check_backend_options
from service.daemon.reset_job import Reset
from service.errors import StateError
from service.wire.commands import Deferred

if TYPE_CHECKING:
    from service.daemon.config import DaemonConfig
    from service.daemon.node import Node

QUIET_COMMANDS = frozenset({"ping", "status", "get_config", "acquire"})
"""Commands not echoed as `command` events (they change nothing)."""


class CommandHandlers:
    """Mixed into Node: the commands of docs/protocol.md."""

    def on_command(self: Node, cmd: str, client: str | None) -> None:
        if cmd not in QUIET_COMMANDS:
            self._event("command", cmd=cmd, client=client)

    def status(self: Node) -> dict[str, Any]:
        ex = self.explorer
        timing = self.loop.summary()
        localizer = self.localizer_work.summary_ms()  # one percentile pass, not two
        timing["localizer_p99_ms"], timing["localizer_max_ms"] = localizer["p99"], localizer["max"]
        scenario = self.config.scenario
        return {
            **self._lifecycle_fields(),
            "configuring": self.reconf is not None, "configure_error": self.configure_error,
            "resetting": self.resetting is not None,
            "estimate": ex.estimate_fields() if ex and ex.estimate else None,
            "lease": {"holder": self.lease.holder_name,
                      "remaining_s": self.lease.remaining_s()},
            "timing": timing, "published": dict(self.pub.sent),
            "commands": {"handled": self.cmd.handled, "errors": self.cmd.errors},
            "backend": self.config.backend.name, "map": self.config.scenario.map,
            "map_warnings": list(self.map_warnings),
            "backend_warnings": list(getattr(self.backend, "warnings", [])),
            "object": scenario.object,
            "hand": None if scenario.object is None else scenario.hand_name,
            "loop_scheduling": self.scheduling and dataclasses.asdict(self.scheduling),
            "sim_truth": self.episode_truth if self.episode_truth is not None else (
                None if self.truth is None else list(self.truth.as_tuple())),
        }

    def config_dict(self: Node) -> dict[str, Any]:
        return self.config.to_dict()

    def _not_configuring(self: Node) -> None:
        if self.reconf is not None:
            raise StateError("a configure is under way; try again when it is answered")
        if self.resetting is not None:
            raise StateError("a reset is under way; try again when it is answered")

    def configure(self: Node, changes: dict[str, Any], command: str = "configure"
                  ) -> Deferred:
        """Validate the whole change now; prepare it off the loop; commit when all of it
        has worked (`_commit`). `command`: the request's name, for its refusals."""
        self.lifecycle.check("configure", command)
        self._not_configuring()
        new = self.config.updated(changes)
        settings = new.run_settings()
        check_backend_options(new, settings)
        port = chosen_port(new.backend.options.get("port"), self.config.backend.options.get(
            "port"), self.operator_ports, self.config.security.serial_ports)
        if port != new.backend.options.get("port"):  # held by its real path from now on
            new = dataclasses.replace(new, backend=dataclasses.replace(
                new.backend, options={**new.backend.options, "port": port}))
        self.link.start()  # (again, if the compute process died)
        rebuild = (self.backend is None or new.backend != self.config.backend
                   or new.backend.name == "sim"
                   or _servos(new) != _servos(self.config)  # another hand on the bus
                   or self.lifecycle.state in (State.UNCONFIGURED, State.FAULT)
                   # the object put back after a drop: a hand on servos starts afresh
                   or bool(self.last_state is not None and self.last_state.dropped))
        deferred = Deferred()
        same_port = self.backend is not None and _same_device(
            new.backend.options.get("port"), self.config.backend.options.get("port"))
        self.reconf = Reconfiguration(new, settings, self.link, deferred,
                                      rebuild_backend=rebuild, fault_count=self.faults,
                                      release=self.backend if rebuild and same_port else None,
                                      recover=self.lifecycle.state is State.FAULT)
        return deferred

    def _commit(self: Node, rc: Reconfiguration) -> None:
        """Everything worked: swap in the new backend, scenario and settings."""
        self.reconf = None
        self._tell_fault(wait=True)  # the old backend's fault, before it goes
        self.configure_error = None
        if rc.backend is not None:
            if self.backend is not None:
                with contextlib.suppress(Exception):  # torque off, port released
                    self.backend.close()
            self.backend, self.truth = rc.backend, rc.truth
            self.last_state = None
            self.lifecycle.valid_read = False
        self.link.send("commit")
        new = rc.new
        episode = 1 if self.explorer is None else self.explorer.episode + 1
        previous = self.explorer
        if previous is not None:
            self._episode_cut(previous.stop("reconfigured"))
        self.explorer = Explorer(self.link, new.run_settings(), first_episode=episode,
                                 truth_at=self.truth_at, hidden=self.hidden)
        if previous is not None:
            self.explorer.keep_estimate(previous)
        self.episode_truth = None
        self.config = new
        self.map_warnings = rc.warnings
        for warning in rc.warnings:
            logging.getLogger("hapticd").warning("map %s: %s", new.scenario.map, warning)
        self.lease.ttl_ns = int(new.lease.ttl_s * 1e9)
        if new.loop.period_ns != self.loop.period_ns or new.loop.overrun != self.loop.overrun:
            self.loop.overrun = new.loop.overrun
            self.loop.retime(new.loop.period_ns)
        self._apply_priority()  # commit runs in the loop's thread
        self._transition("configure")
        self._read()  # a first reading now, so the finger may be activated at once
        for line in rc.rebooted:
            logging.getLogger("hapticd").warning("configure: %s", line)
        rc.deferred.resolve({"state": self.lifecycle.state.value,
                             "warnings": rc.warnings + getattr(rc.backend, "warnings", []),
                             "rebooted": rc.rebooted})

    def activate(self: Node) -> dict[str, Any]:
        if self.lifecycle.state is State.UNCONFIGURED and self.configure_error:
            raise StateError(f"cannot activate while unconfigured: the last configure failed "
                             f"({self.configure_error}); put that right and configure again")
        self.lifecycle.check("activate")
        self._not_configuring()
        self.lifecycle.require_valid_read()
        try:
            self.backend.set_torque(True)
        except HardwareFault as exc:  # e.g. the bus went away while touching down
            self._fault(f"activate failed: {exc}")
            raise
        self._read_now()
        self._transition("activate")
        return {"state": self.lifecycle.state.value}

    def deactivate(self: Node) -> dict[str, Any]:
        self.lifecycle.check("deactivate")
        self._deactivate()
        return {"state": self.lifecycle.state.value}

    def start_exploration(self: Node, repeat: bool) -> Deferred:
        """Start an episode here; the reply comes with its first belief."""
        if self.lifecycle.state is not State.ACTIVE:  # from a fault, activate is refused too
            first = "reset, then activate" if self.lifecycle.state is State.FAULT else "activate"
            raise StateError(f"cannot start exploration while {self.lifecycle.state.value}; "
                             f"{first} first")
        if self.explorer.running:
            raise StateError("already exploring; stop_exploration first")
        if self._hold_until_ns is not None:
            raise StateError("the finger is holding after a lost lease and will stop")
        state = self.last_state
        if state is None or state.moving:
            raise StateError("a step is still under way; try again in a moment")
        if state.dropped:
            raise StateError("the object was dropped: put it back in the hand and configure "
                             "again (the simulator places it anew on configure)")
        self.explorer.start(state, repeat, self.truth_at(state))
        self.starting = Deferred()
        return self.starting

    def stop_exploration(self: Node) -> dict[str, Any]:
        was = bool(self.explorer and self.explorer.running)
        cut = self.explorer.stop("stopped") if self.explorer else None
        self._fail_start(StateError("stopped before the first belief"))
        self._hold_until_ns = None
        self._episode_cut(cut)
        return {"was_exploring": was}

    def reset(self: Node) -> Deferred:
        """Clear the fault: the backend re-opens its port and configures every servo again,
        beside the loop (`reset_job`); if that fails the daemon stays in fault and the reply
        says why."""
        self.lifecycle.check("reset")
        self._not_configuring()
        if self.backend is None:
            raise StateError("no backend: configure first")
        self.resetting = Reset(self.backend, Deferred(), self.faults)
        return self.resetting.deferred

    def _end_reset(self: Node) -> None:
        """The reset's thread is done: turn the lifecycle, or say why not."""
        job, self.resetting = self.resetting, None
        self._tell_fault(wait=True)  # the fault's own event comes before its end
        if job.error is not None:  # still faulted
            job.deferred.fail(job.error)
            return
        if self.faults != job.fault_count:
            with contextlib.suppress(Exception):  # the estop's torque off, now the bus is free
                self.backend.set_torque(False)
            job.deferred.fail(StateError("a fault was latched (an estop?) during the reset; "
                                         "still faulted: reset again"))
            return
        for line in job.rebooted:
            logging.getLogger("hapticd").warning("reset: %s", line)
        self.last_state = None
        self._transition("reset")
        job.deferred.resolve({"state": self.lifecycle.state.value, "rebooted": job.rebooted,
                              "warnings": list(getattr(self.backend, "warnings", []))})

    def estop(self: Node, reason: str) -> dict[str, Any]:
        if self.lifecycle.state is not State.UNCONFIGURED:
            self._fault(f"estop: {reason}", again=True)
        return {"state": self.lifecycle.state.value}

    def reset_stats(self: Node) -> dict[str, Any]:
        self.loop.reset_stats()
        self.localizer_work.reset()
        return {}


def _servos(config: DaemonConfig) -> str | None:
    """What the backend drives besides its own options: the hand holding the object, or
    None for a finger (its chain is a backend option). A held-out check changed
    scenario.hand on a running Dynamixel daemon: accepted, the two-finger backend kept,
    and the next episode failed in the compute process."""
    return None if config.scenario.object is None else config.scenario.hand_name


def _same_device(new: Any, old: Any) -> bool:
    """Whether two port options name one device: the same path, or two names of it (a
    link such as /dev/serial/by-id/... and the /dev/ttyUSB0 it points to). The daemon
    holds its port exclusively, so the old backend must let a device go before a new one
    opens it under any name (a held-out lab moved a running daemon from /dev/pts/1 to a
    link to it and was told another process held the port)."""
    if not (isinstance(new, str) and isinstance(old, str)):
        return False
    if new == old:
        return True
    try:
        return os.path.samefile(new, old)
    except OSError:  # one of them is gone or never was: not the device held
        return False
