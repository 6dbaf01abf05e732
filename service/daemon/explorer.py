"""Exploration sliced across loop ticks: what `run_episode` does, without ever waiting.

Each tick gets the latest reading. The explorer moves through
DECIDE (ask the policy, command a step) -> STEPPING (until the backend reports the step
finished) -> UPDATING (the localizer's anytime `work` under this tick's budget, resumed
next tick until done) -> DECIDE ... until the localizer converges, runs out of candidates
or the step limit is reached. A new move waits for the localizer; a tick never does.

With `offload=True` each update, and each policy choice, runs to completion on a worker
thread instead (for localizers whose `work` slices are longer than a tick); the tick only
checks whether it is done, and the hypotheses viewers see are a snapshot the worker takes
after each update.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from firmware_if.backend import FingerState, StepCommand
from firmware_if.errors import BusTimeoutError
from service.episode.scenario import RunSettings, build_localizer, build_policy, prepare_localizers
from service.localization.localizers.base import (
    Budget,
    Estimate,
    Hypotheses,
    Localizer,
    Measurement,
    update,
)
from service.localization.policies.base import MOVES, Policy, PolicyInput
from service.localization.surface import ContactSurface


class Phase(StrEnum):
    IDLE = "idle"
    DECIDE = "decide"
    STEPPING = "stepping"
    UPDATING = "updating"
    RESTART = "restart"


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
    localizer_ns: int | None = None
    """Localizer work done this tick (None when it did not run)."""
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)


class Explorer:
    """One exploration at a time over a settings' surface; `repeat` runs episodes back to back."""

    def __init__(self, settings: RunSettings, surface: ContactSurface,
                 rng: np.random.Generator | tuple[np.random.Generator, np.random.Generator],
                 step_timeout_s: float = 10.0, *, offload: bool = False,
                 cloud_points: int = 500, first_episode: int = 1) -> None:
        self.settings = settings
        self.offload = offload
        self.cloud_points = cloud_points
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future | None = None
        self._cloud: Cloud | None = None
        self._cloud_current = False
        """Whether `_cloud` shows the belief as it is: between updates it cannot change,
        so the 4 Hz cloud is not re-sorted in every tick that publishes it."""
        self.surface = surface
        self._rng = rng
        """One generator (each episode spawns its localizer's and policy's streams from it),
        or the (localizer, policy) pair `haptic run` uses for the first episode."""
        self.step_timeout_ns = int(step_timeout_s * 1e9)
        self.phase = Phase.IDLE
        self.paused = False
        self.repeat = False
        self.episode = first_episode - 1
        """The current episode's id: numbered on from the previous explorer's (`configure`
        replaces the explorer), so ids are unique while the daemon runs."""
        self.steps = 0
        self._update_ns = 0
        """Localizer time of the update under way (its slices, or the worker's whole)."""
        self._policy_ms = 0.0
        self._blocked = False
        self._belief_step = 0
        """Readings the estimate (and the cloud) include; `steps` runs ahead during a step."""
        self._belief_displacement = np.zeros(3)
        self.localizer: Localizer | None = None
        self.policy: Policy | None = None
        self.estimate: Estimate | None = None
        self.origin = np.zeros(3)
        self.displacement = np.zeros(3)
        self._blocked_here: set[int] = set()
        self._before = 0
        self._step_started_ns = 0
        self._move = -1
        prepare_localizers()  # any algorithm may be asked for later, inside a tick

    @property
    def running(self) -> bool:
        return self.phase is not Phase.IDLE

    def start(self, state: FingerState, repeat: bool = False) -> TickOutput:
        """Begin an episode at the finger's current place (its unknown start pose)."""
        self.repeat = repeat
        self.paused = False
        return self._begin(state)

    def stop(self) -> None:
        self.phase = Phase.IDLE
        self.repeat = False
        self._future = None  # an update still running on the worker is abandoned

    def close(self) -> None:
        """Stop, and let the worker thread (if any) finish on its own."""
        self.stop()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def _worker(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="localizer")
        return self._pool

    def wait_update(self, timeout_s: float | None = None) -> None:
        """Block until offloaded work (update or policy) finishes; for tests, never the loop."""
        future = self._future
        if future is not None:
            future.exception(timeout_s)

    def cloud(self) -> Cloud | None:
        """Hypotheses for viewers, never touching a localizer the worker is updating.

        A sample is taken only between updates, so its count and step are those of the
        same moment; mid-update (sliced) the last complete one is returned, or None."""
        if self.localizer is None:
            return None
        if self.offload and self._future is not None:
            return self._cloud
        if not self._cloud_current and self.phase is not Phase.UPDATING:
            self._cloud = Cloud(self.localizer.hypotheses(limit=self.cloud_points),
                                self.estimate.candidates, self._belief_step)
            self._cloud_current = True
        return self._cloud

    def _begin(self, state: FingerState) -> TickOutput:
        if isinstance(self._rng, tuple):  # the first episode: as `haptic run` seeds it
            (loc_rng, policy_rng), self._rng = self._rng, self._rng[0].spawn(1)[0]
        else:
            loc_rng, policy_rng = self._rng.spawn(2)
        self._future = None
        self._cloud = None
        self.localizer = build_localizer(self.settings, self.surface, loc_rng)
        self._cloud_current = False
        self.policy = build_policy(self.settings)
        self._policy_rng = policy_rng
        self.origin = np.asarray(state.centre, dtype=np.float64)
        self.displacement = np.zeros(3)
        self._blocked_here.clear()
        self.localizer.start(Measurement(step=0, displacement=np.zeros(3), t_ns=state.t_ns))
        self.estimate = self.localizer.estimate()
        self.episode += 1
        self.steps = 0
        self._belief_step, self._belief_displacement = 0, self.displacement
        self.phase = Phase.DECIDE
        return TickOutput(estimate_updated=True, events=[(
            "episode_started", {"episode": self.episode,
                                "candidates": self.estimate.candidates,
                                "settings": self.settings.to_json()})])

    def tick(self, state: FingerState, command_step: Callable[[StepCommand], None],
             budget_deadline_ns: int) -> TickOutput:
        """Advance as far as this tick allows; `command_step` is the backend's."""
        out = TickOutput()
        if self.phase is Phase.RESTART:
            return self._begin(state)
        if self.phase is Phase.STEPPING:
            self._check_step(state)
        if self.phase is Phase.UPDATING and self.offload:
            if self._future is not None and self._future.done():
                # a worker error raises here
                self.estimate, hypotheses, self._update_ns = self._future.result()
                self._cloud = Cloud(hypotheses, self.estimate.candidates, self.steps)
                self._cloud_current = True
                self._future = None
                self._updated(out)
        elif self.phase is Phase.UPDATING:
            t0 = time.monotonic_ns()
            done = self.localizer.work(Budget(deadline_ns=budget_deadline_ns))
            out.localizer_ns = time.monotonic_ns() - t0
            self._update_ns += out.localizer_ns
            if done:
                self.estimate = self.localizer.estimate()
                self._updated(out)
        # The policy gets a tick of its own once the localizer has run in this one, so a
        # tick's work is the larger of the two, not their sum.
        if (self.phase is Phase.DECIDE and not self.paused and out.localizer_ns is None
                and time.monotonic_ns() < budget_deadline_ns):
            self._decide(state, command_step, out)
        return out

    def _updated(self, out: TickOutput) -> None:
        """An update is complete: publish the estimate and the step as `haptic run` records
        it (its JSON's `steps` entry), so a recording can be exported like a run."""
        out.estimate_updated = True
        self.phase = Phase.DECIDE
        self._belief_step, self._belief_displacement = self.steps, self.displacement
        est, belief = self.estimate, self.estimate_fields()
        command = MOVES[self._move] * self.settings.step
        out.events.append(("step", {
            "episode": self.episode, "index": self.steps, "move": self._move,
            "command": [float(command[0]), float(command[1])],
            "measurement": [float(v) for v in self.displacement], "blocked": self._blocked,
            "candidates": est.candidates, "compute_ms": self._update_ns / 1e6,
            "policy_ms": self._policy_ms,
            "estimate": None if est.pose is None else [float(v) for v in est.pose],
            **{k: belief[k] for k in ("position_sd", "heading_sd", "mode_mass")}}))

    def _check_step(self, state: FingerState) -> None:
        if state.steps_done > self._before and not state.moving:
            self.displacement = np.asarray(state.centre, dtype=np.float64) - self.origin
            self._blocked = bool(state.blocked)
            self._update_ns = 0
            if state.blocked:
                self._blocked_here.add(self._move)
            else:
                self._blocked_here.clear()
            command = MOVES[self._move] * self.settings.step
            m = Measurement(step=self.steps, displacement=self.displacement,
                            blocked=state.blocked, t_ns=state.t_ns,
                            command=(float(command[0]), float(command[1])))
            if self.offload:
                self._future = self._worker().submit(_full_update, self.localizer, m,
                                                     self.cloud_points)
            else:
                self.localizer.begin_update(m)
            self._cloud_current = False
            self.phase = Phase.UPDATING
        elif time.monotonic_ns() - self._step_started_ns > self.step_timeout_ns:
            raise BusTimeoutError(f"step {self.steps} did not finish within "
                                  f"{self.step_timeout_ns / 1e9:g} s")

    def _decide(self, state: FingerState, command_step: Callable[[StepCommand], None],
                out: TickOutput) -> None:
        est = self.estimate
        if est.converged or est.candidates == 0 or self.steps >= self.settings.max_steps:
            reason = ("converged" if est.converged else
                      "eliminated" if est.candidates == 0 else "out_of_steps")
            fields = self.estimate_fields()
            del fields["step"], fields["displacement"]
            out.events.append(("episode_done", {**fields, "steps": self.steps,
                                                "reason": reason}))
            self.phase = Phase.RESTART if self.repeat else Phase.IDLE
            return
        args = (self.localizer, self.policy, self.displacement[:2].copy(),
                frozenset(self._blocked_here), self.surface, self.settings.step,
                self._policy_rng, self.settings.walls)
        if not self.offload:
            self._move, self._policy_ms = _choose(*args)
        elif self._future is None:  # the policy runs on the worker too; command when done
            self._future = self._worker().submit(_choose, *args)
            return
        elif not self._future.done():
            return
        else:
            (self._move, self._policy_ms), self._future = self._future.result(), None
        dx, dy = MOVES[self._move] * self.settings.step
        self._before = state.steps_done
        command_step(StepCommand(float(dx), float(dy)))
        self._step_started_ns = time.monotonic_ns()
        self.steps += 1
        self.phase = Phase.STEPPING

    def estimate_fields(self) -> dict[str, Any]:
        """The `estimate` topic's fields (docs/protocol.md)."""
        est = self.estimate

        def num(v: float) -> float | None:
            return float(v) if v is not None and np.isfinite(v) else None

        return {
            "episode": self.episode, "step": self._belief_step,
            "pose": None if est is None or est.pose is None else list(est.pose),
            "candidates": 0 if est is None else est.candidates,
            "converged": bool(est and est.converged),
            "position_sd": None if est is None else num(est.position_sd),
            "heading_sd": None if est is None else num(est.heading_sd),
            "mode_mass": None if est is None else num(est.mode_mass),
            "runner_up": None if est is None or est.runner_up is None else [
                float(v) for v in est.runner_up],
            "runner_up_mass": None if est is None or est.runner_up is None else num(
                est.runner_up_mass),
            "displacement": [float(v) for v in self._belief_displacement],
        }


def _full_update(localizer: Localizer, m: Measurement, cloud_points: int
                 ) -> tuple[Estimate, Hypotheses, int]:
    """Worker thread: one whole update (and its duration, ns), then the estimate and a
    cloud snapshot."""
    t0 = time.monotonic_ns()
    update(localizer, m)
    took = time.monotonic_ns() - t0
    return localizer.estimate(), localizer.hypotheses(limit=cloud_points), took


def _choose(localizer: Localizer, policy: Policy, displacement: np.ndarray,
            blocked: frozenset[int], surface: ContactSurface, step: float,
            rng: np.random.Generator, walls: bool) -> tuple[int, float]:
    """The policy's next move and its time in ms (on the worker thread when offloaded)."""
    t0 = time.perf_counter()
    view = PolicyInput(hypotheses=localizer.hypotheses(), displacement=displacement,
                       blocked=blocked, surface=surface, step_length=step, rng=rng,
                       walls=walls, estimate=localizer.estimate())
    return int(policy.next_move(view)), (time.perf_counter() - t0) * 1e3
