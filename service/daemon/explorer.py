"""Exploration as the loop sees it: what `run_episode` does, without ever waiting.

The localizer and the policy live in the compute process (`service.daemon.worker`); this
is the loop's half. Each tick gets the latest reading and the compute process's replies:

    START (the first belief and move are being computed) -> STEPPING (until the backend
    reports the step finished) -> UPDATING (the reading is being taken in, and the next
    move chosen) -> STEPPING ... until the localizer converges, runs out of candidates or
    the step limit is reached; with `repeat`, RESTART begins the next episode.

A tick only sends small requests and reads small replies: its cost does not depend on the
localizer's.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from firmware_if.backend import FingerState, StepCommand
from firmware_if.errors import BusTimeoutError
from service.daemon.worker_link import WorkerDied, WorkerLink
from service.episode.scenario import RunSettings
from service.errors import ServiceError
from service.localization.localizers.base import Hypotheses
from service.localization.policies.base import MOVES
from service.wire.envelope import Message


class Phase(StrEnum):
    IDLE = "idle"
    DECIDE = "decide"
    """The compute process is building the episode's localizer and choosing a first move."""
    STEPPING = "stepping"
    UPDATING = "updating"
    RESTART = "restart"


class ComputeError(ServiceError):
    """The compute process refused or failed a request; `code` as in the protocol."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Cloud:
    """Hypotheses for viewers with the count and step they belong to: all from one moment."""

    hypotheses: Hypotheses
    total: int
    """Hypotheses the localizer held when the sample was taken."""
    step: int


@dataclass
class TickOutput:
    """What happened in one tick, for the node to publish."""

    estimate_updated: bool = False
    localizer_ms: float | None = None
    """The compute process's time for the update (and first build) that finished this tick."""
    started: bool = False
    """An episode's first belief arrived (`start_exploration` can be answered)."""
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)


class Explorer:
    """One exploration at a time; `repeat` runs episodes back to back."""

    def __init__(self, link: WorkerLink, settings: RunSettings, step_timeout_s: float = 10.0,
                 *, first_episode: int = 1,
                 truth_at: Callable[[FingerState], list[float] | None] | None = None) -> None:
        self.link = link
        self._truth_at = truth_at
        """The simulator's hidden pose at the finger's place (for `repeat`'s episodes)."""
        self.settings = settings
        self.step_timeout_ns = int(step_timeout_s * 1e9)
        self.phase = Phase.IDLE
        self.paused = False
        self.repeat = False
        self.episode = first_episode - 1
        """The current episode's id: numbered on from the previous explorer's (`configure`
        replaces the explorer), so ids are unique while the daemon runs."""
        self.steps = 0
        self.estimate: dict[str, Any] | None = None
        self.candidates = 0
        self.truth: list[float] | None = None
        self.true_pose_eliminated: bool | None = None
        self._cloud: Cloud | None = None
        self._req = 0
        """The request whose reply the explorer waits for (older replies are dropped)."""
        self._policy_ms = 0.0
        self._move = -1
        self._next_move: int | None = None
        self._blocked = False
        self._belief_step = 0
        self._belief_displacement = np.zeros(3)
        self.origin = np.zeros(3)
        self.displacement = np.zeros(3)
        self._blocked_here: set[int] = set()
        self._before = 0
        self._step_started_ns = 0

    @property
    def running(self) -> bool:
        return self.phase is not Phase.IDLE

    def start(self, state: FingerState, repeat: bool = False,
              truth: list[float] | None = None) -> None:
        """Begin an episode at the finger's current place (its unknown start pose); its
        first belief arrives in a later tick (`TickOutput.started`)."""
        self.repeat = repeat
        self.paused = False
        self._begin(state, truth)

    def stop(self) -> None:
        if self.phase is not Phase.IDLE:
            with contextlib.suppress(WorkerDied):  # a dead process has nothing to cancel
                self._req = self.link.send("cancel")
        self.phase = Phase.IDLE
        self.repeat = False
        self._next_move = None  # a move held back by a pause ends with its episode

    def cloud(self) -> Cloud | None:
        return self._cloud

    def _begin(self, state: FingerState, truth: list[float] | None) -> None:
        self.episode += 1
        self.steps = 0
        self.truth = truth
        self.true_pose_eliminated = None
        self.origin = np.asarray(state.centre, dtype=np.float64)
        self.displacement = np.zeros(3)
        self._belief_step, self._belief_displacement = 0, self.displacement
        self._blocked_here.clear()
        self._cloud = None
        self._next_move = None
        self._req = self.link.send("start", truth=truth, t_ns=state.t_ns,
                                   decide=self.settings.max_steps > 0)
        self.phase = Phase.DECIDE

    def tick(self, state: FingerState, command_step: Callable[[StepCommand], None],
             replies: list[Message]) -> TickOutput:
        """Advance as far as this tick allows; `replies` are the compute process's."""
        out = TickOutput()
        if self.phase is Phase.RESTART:
            self._begin(state, None if self._truth_at is None else self._truth_at(state))
            return out
        for msg in replies:
            if int(msg.get("req", -1)) != self._req or self.phase is Phase.IDLE:
                continue  # an answer to a request the explorer has moved past
            if msg.type == "error":
                self.phase = Phase.IDLE
                raise ComputeError(str(msg.get("code")), str(msg.get("message")))
            if msg.type == "belief":
                self._on_belief(msg, out)
        if self.phase is Phase.STEPPING:
            self._check_step(state)
        if self._next_move is not None and not self.paused and self.phase is Phase.DECIDE:
            self._command(state, command_step)
        return out

    def _on_belief(self, msg: Message, out: TickOutput) -> None:
        first = self.phase is Phase.DECIDE and self.steps == 0
        self.estimate = msg["estimate"]
        self.candidates = int(self.estimate["candidates"])
        self.true_pose_eliminated = msg.get("true_pose_eliminated")
        self._belief_step, self._belief_displacement = self.steps, self.displacement
        self._cloud = Cloud(Hypotheses(np.asarray(msg["poses"]), np.asarray(msg["weights"])),
                            self.candidates, self.steps)
        out.estimate_updated = True
        out.localizer_ms = float(msg["update_ms"])
        if first:
            out.started = True
            out.events.append(("episode_started", {
                "episode": self.episode, "candidates": self.candidates,
                "settings": self.settings.to_json(), "truth": self.truth}))
        else:
            command = MOVES[self._move] * self.settings.step
            out.events.append(("step", {
                "episode": self.episode, "index": self.steps, "move": self._move,
                "command": [float(command[0]), float(command[1])],
                "measurement": [float(v) for v in self.displacement],
                "blocked": self._blocked, "candidates": self.candidates,
                "compute_ms": float(msg["update_ms"]), "policy_ms": self._policy_ms,
                "estimate": self.estimate["pose"],
                **{k: self.estimate[k] for k in ("position_sd", "heading_sd", "mode_mass")}}))
        self._policy_ms = float(msg["policy_ms"])
        est = self.estimate
        if est["converged"] or self.candidates == 0 or self.steps >= self.settings.max_steps:
            reason = ("converged" if est["converged"] else
                      "eliminated" if self.candidates == 0 else "out_of_steps")
            out.events.append(("episode_done", {
                "episode": self.episode, **est, "steps": self.steps, "reason": reason,
                "true_pose_eliminated": self.true_pose_eliminated}))
            self.phase = Phase.RESTART if self.repeat else Phase.IDLE
            self._next_move = None
            return
        self._next_move = msg.get("move")
        self.phase = Phase.DECIDE

    def _command(self, state: FingerState, command_step: Callable[[StepCommand], None]) -> None:
        self._move, self._next_move = int(self._next_move), None
        dx, dy = MOVES[self._move] * self.settings.step
        self._before = state.steps_done
        command_step(StepCommand(float(dx), float(dy)))
        self._step_started_ns = time.monotonic_ns()
        self.steps += 1
        self.phase = Phase.STEPPING

    def _check_step(self, state: FingerState) -> None:
        if state.steps_done > self._before and not state.moving:
            self.displacement = np.asarray(state.centre, dtype=np.float64) - self.origin
            self._blocked = bool(state.blocked)
            if state.blocked:
                self._blocked_here.add(self._move)
            else:
                self._blocked_here.clear()
            command = MOVES[self._move] * self.settings.step
            self._req = self.link.send(
                "update", measurement={
                    "step": self.steps, "displacement": [float(v) for v in self.displacement],
                    "blocked": self._blocked, "t_ns": state.t_ns,
                    "command": [float(command[0]), float(command[1])]},
                blocked_here=sorted(self._blocked_here),
                displacement=[float(v) for v in self.displacement[:2]],
                decide=self.steps < self.settings.max_steps)
            self.phase = Phase.UPDATING
        elif time.monotonic_ns() - self._step_started_ns > self.step_timeout_ns:
            raise BusTimeoutError(f"step {self.steps} did not finish within "
                                  f"{self.step_timeout_ns / 1e9:g} s")

    def estimate_fields(self) -> dict[str, Any]:
        """The `estimate` topic's fields (docs/protocol.md)."""
        est = self.estimate or {"pose": None, "candidates": 0, "converged": False,
                                "position_sd": None, "heading_sd": None, "mode_mass": None,
                                "runner_up": None, "runner_up_mass": None}
        return {"episode": self.episode, "step": self._belief_step, **est,
                "displacement": [float(v) for v in self._belief_displacement]}
