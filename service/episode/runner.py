"""The episode runner: backend + localizer + policy, one step at a time, everything recorded."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from firmware_if.backend import Backend, FingerState, StepCommand
from firmware_if.errors import BusTimeoutError, HardwareFault
from service.localization.localizers.base import (
    Estimate,
    Localizer,
    Measurement,
    background,
    settle,
    update,
)
from service.localization.policies.base import MOVES, Policy, PolicyInput
from service.localization.surface import ContactSurface


@dataclass(frozen=True)
class StepRecord:
    index: int
    move: int
    command: tuple[float, float]
    measurement: tuple[float, float, float]
    blocked: bool
    candidates: int
    compute_ms: float
    """Localizer update time for this step."""
    policy_ms: float
    estimate: tuple[float, float, float] | None
    background_ms: float = 0.0
    """The localizer's work between updates (`Localizer.background`) while this step's move
    was under way: it delays neither the move nor the update."""
    settle_ms: float = 0.0
    """The background finished after this step's reading, before the next move, because
    the declaration waited only on it (`settle`): it delays that move, never the update."""
    position_sd: float = float("nan")
    """Spread of the hypotheses after this step (m, rad) and the leading mode's probability,
    as the localizer's Estimate gives them (NaN where it has none)."""
    heading_sd: float = float("nan")
    mode_mass: float = float("nan")


@dataclass
class EpisodeResult:
    steps: list[StepRecord] = field(default_factory=list)
    initial_candidates: int = 0
    estimate: Estimate | None = None
    fault: str | None = None
    """What a latched fault (a lost port, a servo's error) said when it cut the step after
    the last: the episode ended there, and what it had found stands."""
    interrupted: str | None = None
    """The signal that cut the step after the last (`kept_on_interrupt`)."""

    @property
    def converged(self) -> bool:
        return bool(self.estimate and self.estimate.converged)

    @property
    def ended(self) -> str:
        """Why the episode ended, in the words of the daemon's `episode_done` reason:
        `converged`, `eliminated` (no hypothesis left), `fault`, `interrupted` or
        `out_of_steps`."""
        if self.fault is not None:
            return "fault"
        if self.interrupted is not None:
            return "interrupted"
        if self.converged:
            return "converged"
        if self.estimate is None or self.estimate.candidates == 0:
            return "eliminated"
        return "out_of_steps"


def execute_step(backend: Backend, step: StepCommand, timeout_s: float = 10.0) -> FingerState:
    """Command a step and poll until the backend reports it finished."""
    before = backend.read_state().steps_done
    backend.command_step(step)
    deadline = time.monotonic() + timeout_s
    while True:
        state = backend.read_state()
        if state.fault:  # a latched fault (a lost port, a servo's error): no step will finish
            raise HardwareFault(f"the finger faulted during a step: {state.fault}")
        if not state.moving and state.steps_done > before:
            return state
        if time.monotonic() > deadline:
            raise BusTimeoutError(f"step did not finish within {timeout_s} s")
        time.sleep(0.001)


class Interruptible(Protocol):
    """An episode's result that can say a signal cut it."""

    interrupted: str | None


@contextmanager
def kept_on_interrupt(result: Interruptible, keep: bool) -> Iterator[None]:
    """With `keep`, Ctrl-C or a stop signal ends the block, and with it the episode, with
    what it had found (`result.interrupted` names the signal) instead of unwinding through
    the caller: a command's `--json` keeps the steps taken (a held-out check lost 11-14
    steps on servos). A step cut while under way is not one."""
    try:
        yield
    except KeyboardInterrupt as exc:
        if not keep:
            raise
        result.interrupted = str(exc) or "SIGINT"  # `tools.signals.Interrupted` names it


def run_episode(backend: Backend, localizer: Localizer, policy: Policy, *,
                surface: ContactSurface, step_length: float, max_steps: int,
                rng: np.random.Generator, walls: bool = False, planar: bool = False,
                on_step: Callable[[StepRecord], None] | None = None,
                on_start: Callable[[], None] | None = None,
                keep_on_interrupt: bool = False) -> EpisodeResult:
    """Explore until the localizer converges or `max_steps` steps are taken (or, with
    `keep_on_interrupt`, until Ctrl-C or a stop signal: `kept_on_interrupt`)."""
    origin = np.asarray(backend.read_state().centre)
    localizer.start(Measurement(step=0, displacement=np.zeros(3)))
    result = EpisodeResult()
    estimate = localizer.estimate()
    result.initial_candidates = estimate.candidates
    if on_start:
        on_start()
    displacement = np.zeros(3)
    blocked_here: set[int] = set()
    recorded = estimate  # the belief of the last step recorded (an interrupt keeps it)
    with kept_on_interrupt(result, keep_on_interrupt):
        for index in range(1, max_steps + 1):
            if estimate.converged or estimate.candidates == 0:
                break
            t0 = time.perf_counter()
            view = PolicyInput(hypotheses=localizer.hypotheses(), displacement=displacement[:2],
                               blocked=frozenset(blocked_here), surface=surface,
                               step_length=step_length, rng=rng, walls=walls,
                               estimate=estimate, planar=planar)
            move = policy.next_move(view)
            policy_ms = (time.perf_counter() - t0) * 1e3
            t0 = time.perf_counter()
            background(localizer)  # while the move is under way (the daemon's worker overlaps them)
            background_ms = (time.perf_counter() - t0) * 1e3
            command = MOVES[move] * step_length
            try:
                state = execute_step(backend, StepCommand(float(command[0]), float(command[1])))
            except HardwareFault as exc:  # the cut step tells nothing: end with what was found
                result.fault = str(exc)
                break
            displacement = np.asarray(state.centre) - origin
            if state.blocked:
                blocked_here.add(move)
            else:
                blocked_here.clear()
            t0 = time.perf_counter()
            update(localizer, Measurement(step=index, displacement=displacement,
                                          blocked=state.blocked, t_ns=state.t_ns,
                                          command=(float(command[0]), float(command[1]))))
            compute_ms = (time.perf_counter() - t0) * 1e3
            estimate, settle_ms = localizer.estimate(), 0.0
            if estimate.pending:  # the background a declaration waits on, before another move
                t0 = time.perf_counter()
                estimate = settle(localizer, estimate)
                settle_ms = (time.perf_counter() - t0) * 1e3
            record = StepRecord(index=index, move=move,
                                command=(float(command[0]), float(command[1])),
                                measurement=tuple(float(v) for v in displacement),
                                blocked=state.blocked, candidates=estimate.candidates,
                                compute_ms=compute_ms, policy_ms=policy_ms, estimate=estimate.pose,
                                background_ms=background_ms, settle_ms=settle_ms,
                                position_sd=estimate.position_sd, heading_sd=estimate.heading_sd,
                                mode_mass=estimate.mode_mass)
            result.steps.append(record)
            recorded = estimate
            if on_step:
                on_step(record)
    # cut between a step's update and its record, the newer belief would stand beside
    # steps that do not hold its reading
    result.estimate = estimate if result.interrupted is None else recorded
    return result
