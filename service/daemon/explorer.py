"""Exploration as the loop sees it: what `run_episode` (a finger) and `run_hand_episode`
(a hand) do, without ever waiting.

The localizer and the policy live in the compute process (`service.daemon.worker`); this
is the loop's half, the same for a finger and a hand (a finger is a hand of one): it sends
the whole hand's reading, commands the `HandCommand` the compute process chose, and
publishes what the compute process says happened. Each tick gets the latest reading and
the compute process's replies:

    START (the first belief and move are being computed) -> STEPPING (until the backend
    reports the step finished) -> UPDATING (the reading is being taken in, and the next
    move chosen) -> STEPPING ... until the compute process says the episode is done
    (converged, no candidates, out of steps; a hand also: dropped, no safe move); with
    `repeat`, RESTART begins the next episode.

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

from firmware_if.backend import FingerMove, HandCommand, HandState
from firmware_if.errors import BusTimeoutError
from service.daemon.worker_link import WorkerDied, WorkerLink
from service.episode.hand_scenario import HandSettings
from service.episode.scenario import RunSettings
from service.errors import ServiceError
from service.localization.localizers.base import Hypotheses
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

    def __init__(self, link: WorkerLink, settings: RunSettings | HandSettings,
                 step_timeout_s: float = 10.0, *, first_episode: int = 1,
                 truth_at: Callable[[HandState], list[float] | None] | None = None,
                 hidden: Callable[[], dict[str, Any]] | None = None) -> None:
        self.link = link
        self._truth_at = truth_at
        """The simulator's hidden pose at the hand's place (for `repeat`'s episodes)."""
        self._hidden = hidden
        """The simulator's hidden state now (a hand's object pose and grasp quality), sent
        with each reading for the record; None on hardware."""
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
        """The localizer's latest estimate (`service.daemon.finger_compute.estimate_fields`)."""
        self._topic: dict[str, Any] = {}
        """The rest of the `estimate` topic for it: kind, step, displacement, quality."""
        self.candidates = 0
        self.truth: list[float] | None = None
        self._cloud: Cloud | None = None
        self._req = 0
        """The request whose reply the explorer waits for (older replies are dropped)."""
        self._next: HandCommand | None = None
        self._before = 0
        self._step_started_ns = 0
        self._started = False
        """The episode under way has had its first belief (`episode_started` is out)."""
        self._undo: tuple[Any, ...] = ()
        """What `_begin` replaced, put back when an episode ends before its first belief:
        a start refused (a fault at once) used up an id and wiped the estimate."""

    @property
    def running(self) -> bool:
        return self.phase is not Phase.IDLE

    def start(self, state: HandState, repeat: bool = False,
              truth: list[float] | None = None) -> None:
        """Begin an episode where the hand is now (its unknown start pose); its first
        belief arrives in a later tick (`TickOutput.started`)."""
        self.repeat = repeat
        self.paused = False
        self._begin(state, truth)

    def stop(self, reason: str = "stopped") -> dict[str, Any] | None:
        """Stop the episode under way; returns its `episode_done` fields (cut short for
        `reason`, the estimate as of the cut), or None when none was under way."""
        cut = None
        if self.phase not in (Phase.IDLE, Phase.RESTART):  # RESTART: the last one is done
            with contextlib.suppress(WorkerDied):  # a dead process has nothing to cancel
                self._req = self.link.send("cancel")
        if not self._forget_unstarted() and self.phase not in (Phase.IDLE, Phase.RESTART):
            est = {k: v for k, v in self.estimate_fields().items()
                   if k not in ("step", "kind", "displacement", "predicted_quality", "quality")}
            # a step commanded but not yet read has no `step` event: it is not counted
            done = self.steps - (self.phase in (Phase.STEPPING, Phase.UPDATING))
            cut = {**est, "steps": done, "reason": reason,
                   "true_pose_eliminated": None, **({"dropped": False}
                                                    if self.kind == "hand" else {})}
        self.phase = Phase.IDLE
        self.repeat = False
        self._next = None  # a move held back by a pause ends with its episode
        return cut

    def _forget_unstarted(self) -> bool:
        """Undo `_begin` if the episode never had its first belief: it never began. Whether
        it did so."""
        if self.phase is not Phase.DECIDE or self._started:
            return False
        (self.episode, self.steps, self.truth, self.estimate, self._topic, self._cloud,
         self.candidates) = self._undo
        return True

    def cloud(self) -> Cloud | None:
        return self._cloud

    def keep_estimate(self, previous: Explorer) -> None:
        """Show `previous`'s last estimate (under its episode id) until an episode begins
        here: a configure, a recovery onto a new port say, loses nothing it already had."""
        if previous.estimate is not None and previous.episode == self.episode:
            self.estimate, self._topic = previous.estimate, dict(previous._topic)

    def _begin(self, state: HandState, truth: list[float] | None) -> None:
        self._undo = (self.episode, self.steps, self.truth, self.estimate, self._topic,
                      self._cloud, self.candidates)
        self._started = False
        self.episode += 1
        self.steps = 0
        self.truth = truth
        self.estimate = None  # the last episode's is not this one's
        self._topic = {}
        self._cloud = None
        self._next = None
        self._req = self.link.send("start", truth=truth, reading=self._reading(state))
        self.phase = Phase.DECIDE

    def tick(self, state: HandState, command_hand: Callable[[HandCommand], None],
             replies: list[Message]) -> TickOutput:
        """Advance as far as this tick allows; `replies` are the compute process's."""
        out = TickOutput()
        if self.phase is Phase.RESTART:
            if state.dropped:  # nothing left to hold: `repeat` began 242 episodes in 5 s
                self.phase, self.repeat = Phase.IDLE, False
            elif not self.paused:  # a lost lease's hold starts no episode
                self._begin(state, None if self._truth_at is None else self._truth_at(state))
            return out
        for msg in replies:
            if int(msg.get("req", -1)) != self._req or self.phase is Phase.IDLE:
                continue  # an answer to a request the explorer has moved past
            if msg.type == "error":
                self._forget_unstarted()  # a start the compute process refused
                self.phase = Phase.IDLE
                raise ComputeError(str(msg.get("code")), str(msg.get("message")))
            if msg.type == "belief":
                self._on_belief(msg, out)
        if self.phase is Phase.STEPPING:
            self._check_step(state)
        if self._next is not None and not self.paused and self.phase is Phase.DECIDE:
            self._command(state, command_hand)
        return out

    def _on_belief(self, msg: Message, out: TickOutput) -> None:
        first = self.phase is Phase.DECIDE and self.steps == 0
        self.estimate = msg["estimate"]
        self._topic = msg["topic"]
        self.candidates = int(self.estimate["candidates"])
        self._cloud = Cloud(Hypotheses(np.asarray(msg["poses"]), np.asarray(msg["weights"])),
                            self.candidates, self.steps)
        out.estimate_updated = True
        out.localizer_ms = float(msg["update_ms"])
        if first:
            self._started = True
            out.started = True
            out.events.append(("episode_started", {
                "episode": self.episode, "candidates": self.candidates,
                "settings": self.settings.to_json(), "truth": self.truth}))
        for name, fields in msg["events"]:
            out.events.append((name, {"episode": self.episode, **fields}))
        if msg["done"]:
            self.phase = Phase.RESTART if self.repeat else Phase.IDLE
            self._next = None
            return
        self._next = HandCommand(tuple(None if m is None else FingerMove(*m)
                                       for m in msg["command"]))
        self.phase = Phase.DECIDE

    def _command(self, state: HandState, command_hand: Callable[[HandCommand], None]) -> None:
        command, self._next = self._next, None
        self._before = state.fingers[0].steps_done
        command_hand(command)
        self._step_started_ns = time.monotonic_ns()
        self.steps += 1
        self.phase = Phase.STEPPING

    def _check_step(self, state: HandState) -> None:
        if state.fingers[0].steps_done > self._before and not state.moving:
            self._req = self.link.send("update", step=self.steps,
                                       reading=self._reading(state))
            self.phase = Phase.UPDATING
        elif time.monotonic_ns() - self._step_started_ns > self.step_timeout_ns:
            raise BusTimeoutError(f"step {self.steps} did not finish within "
                                  f"{self.step_timeout_ns / 1e9:g} s")

    def _reading(self, state: HandState) -> dict[str, Any]:
        """The hand's reading as the compute process takes it (plain numbers)."""
        return {"t_ns": state.t_ns, "dropped": bool(state.dropped),
                "fingers": [{"centre": [float(v) for v in f.centre],
                             "joints": [float(q) for q in f.joints], "blocked": bool(f.blocked)}
                            for f in state.fingers],
                **(self._hidden() if self._hidden is not None else {})}

    def estimate_fields(self) -> dict[str, Any]:
        """The `estimate` topic's fields (docs/protocol.md)."""
        est = self.estimate or {"pose": None, "candidates": 0, "converged": False,
                                "position_sd": None, "heading_sd": None, "mode_mass": None,
                                "runner_up": None, "runner_up_mass": None}
        return {"episode": self.episode, "step": 0, "kind": self.kind, "displacement": None,
                "predicted_quality": None, "quality": None, **est, **self._topic}

    @property
    def kind(self) -> str:
        """What the episode localizes: 'finger' (a finger on a map) or 'hand' (an object
        held by a hand)."""
        return "hand" if isinstance(self.settings, HandSettings) else "finger"
