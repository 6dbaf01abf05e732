"""A hand episode: explore a held object until its pose is known, without dropping it.

`run_hand_episode` drives any hand (the simulated one, later the servos) step by step: the
grasp-gated policy decides, the hand moves, the localizer updates, everything is recorded.
`simulate_hand` builds a seeded episode from settings: what `haptic run --object` and
`haptic bench grasp` call.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_if.backend import HandCommand, HandState
from firmware_if.errors import BusTimeoutError, HardwareFault
from service.episode.hand_scenario import (
    HandParts,
    HandScore,
    HandSettings,
    build_localizer,
    build_policy,
    draw_truth,
    load_parts,
    score,
    streams,
)
from service.episode.hand_step import (
    HandStepper,
    HandStepRecord,
    json_number,
    plane_centres,
    step_json,
)
from service.episode.runner import kept_on_interrupt
from service.localization.localizers.base import Budget, Estimate, Hypotheses
from service.localization.objects.contour import Contour
from service.localization.policies.grasp_gated import GraspGatedPolicy

SNAPSHOT_LIMIT = 400


@dataclass
class HandEpisodeResult:
    steps: list[HandStepRecord] = field(default_factory=list)
    estimate: Estimate | None = None
    dropped: bool = False
    stuck: bool = False
    """The policy found no safe move left."""
    fault: str | None = None
    """What a latched fault (a lost port, a servo's error) said when it cut the step after
    the last: the episode ended there, and what it had found stands."""
    interrupted: str | None = None
    """The signal that cut the step after the last (`runner.kept_on_interrupt`)."""
    start_centres: tuple[tuple[float, float], ...] = ()

    @property
    def converged(self) -> bool:
        return bool(self.estimate and self.estimate.converged)


def execute(hand: Any, command: HandCommand, timeout_s: float = 10.0) -> HandState:
    """Command a hand step and poll until the hand reports it finished."""
    before = hand.read_hand().fingers[0].steps_done
    hand.command_hand(command)
    deadline = time.monotonic() + timeout_s
    while True:
        state = hand.read_hand()
        fault = next((f.fault for f in state.fingers if f.fault), None)
        if fault:  # a latched fault (a lost port, a servo's error): no step will finish
            raise HardwareFault(f"the hand faulted during a step: {fault}")
        if not state.moving and state.fingers[0].steps_done > before:
            return state
        if time.monotonic() > deadline:
            raise BusTimeoutError(f"hand step did not finish within {timeout_s} s")
        time.sleep(0.001)


def run_hand_episode(hand: Any, localizer: Any, policy: GraspGatedPolicy, parts: HandParts,
                     settings: HandSettings, *,
                     on_step: Callable[[HandStepRecord], None] | None = None,
                     truth: Callable[[], tuple[float, float, float]] | None = None,
                     quality: Callable[[], tuple[float, float]] | None = None,
                     keep_on_interrupt: bool = False) -> HandEpisodeResult:
    """Explore until the localizer converges, `max_steps` pass, the object drops or no safe
    move is left (or, with `keep_on_interrupt`, until Ctrl-C or a stop signal:
    `runner.kept_on_interrupt`). `truth`/`quality` read the simulator's hidden state for
    the record (`quality`: the grasp's after the step, and its least during it)."""
    state = hand.read_hand()
    stepper = HandStepper(localizer, policy, parts, settings)
    result = HandEpisodeResult(start_centres=tuple(map(tuple, plane_centres(state).tolist())))
    stepper.start(state)
    recorded = stepper.estimate  # the belief of the last step recorded (an interrupt keeps it)
    with kept_on_interrupt(result, keep_on_interrupt):
        for index in range(1, settings.max_steps + 1):
            if stepper.settled:
                break
            decision = stepper.decide(state)
            if decision.command is None:
                result.stuck = True
                break
            try:
                state = execute(hand, decision.command)
            except HardwareFault as exc:  # the cut step tells nothing: end with what was found
                result.fault = str(exc)
                break
            result.dropped = result.dropped or state.dropped
            measurement = stepper.observe(index, decision, state)
            compute_ms = settle_ms = 0.0
            if measurement is not None:
                t0 = time.perf_counter()
                localizer.begin_update(measurement)
                while not localizer.work(Budget.unlimited()):
                    pass
                compute_ms = (time.perf_counter() - t0) * 1e3
                stepper.updated()
                settle_ms = stepper.confirm()  # what a declaration waits on, before another move
            now, least = (float("nan"), float("nan")) if quality is None else quality()
            record = stepper.record(index, decision, state, compute_ms=compute_ms,
                                    settle_ms=settle_ms, quality=now, least_quality=least,
                                    truth=None if truth is None else truth())
            result.steps.append(record)
            recorded = stepper.estimate
            if on_step:
                on_step(record)
            if result.dropped:
                break
    # cut between a step's update and its record, the newer belief would stand beside
    # steps that do not hold its reading
    result.estimate = stepper.estimate if result.interrupted is None else recorded
    return result


@dataclass
class HandEpisodeReport:
    settings: HandSettings
    start: tuple[float, float, float]
    truth: tuple[float, float, float]
    """The object's true pose at the end."""
    result: HandEpisodeResult
    score: HandScore
    parts: HandParts
    min_quality: float
    """The least true grasp quality at any substep of any move (newtons)."""
    start_quality: float
    snapshots: dict[int, Hypotheses] = field(default_factory=dict)
    truth_known: bool = True
    """False for a run on servos after a manipulation moved the object where it cannot see:
    `truth` is then the start and the run is not scored."""

    def to_json(self) -> dict[str, Any]:
        est = self.result.estimate
        return {
            "settings": self.settings.to_json(),
            "object": self.parts.contour.name,
            "object_origin": list(self.parts.contour.origin),
            "object_axis": list(self.parts.contour.axis),
            "hand": self.parts.hand.name,
            "start": list(self.start),
            "truth": list(self.truth),
            "truth_known": self.truth_known,
            "start_centres": [list(c) for c in self.result.start_centres],
            "steps": [step_json(s) for s in self.result.steps],
            "estimate": None if est is None or est.pose is None else {
                "x": est.pose[0], "z": est.pose[1], "heading": est.pose[2],
                "candidates": est.candidates, "position_sd": json_number(est.position_sd),
                "heading_sd": json_number(est.heading_sd), "mode_mass": json_number(est.mode_mass)},
            "converged": self.result.converged,
            "success": self.score.success,
            "wrong_declaration": self.score.wrong_declaration,
            "dropped": self.result.dropped,
            "stuck": self.result.stuck,
            "fault": self.result.fault,
            "interrupted": self.result.interrupted,
            "position_error": self.score.position_error,
            "heading_error": self.score.heading_error,
            "min_quality": json_number(self.min_quality),
            "start_quality": json_number(self.start_quality),
        }


def seeded_world(settings: HandSettings, parts: HandParts
                 ) -> tuple[tuple[float, float, float], Contour, np.random.Generator]:
    """The seed's simulated world: the object's start pose, its outline as the hand meets
    it (B2's mismatch drawn first from the world stream) and that stream after the draw.
    The start is drawn in that world, so a run on servos and the daemon's setup know the
    pose the simulated hand holds."""
    from sim_backend.hand import perturbed_contour  # chosen at run time

    truth_rng, world_rng, _, _ = streams(settings.seed)
    noise = settings.noise_spec
    world = perturbed_contour(parts.contour, noise.surface_sigma, noise.surface_correlation,
                              world_rng)
    return draw_truth(settings, parts, truth_rng, world), world, world_rng


def simulated_hand(settings: HandSettings, parts: HandParts, step_duration_s: float = 0.0
                   ) -> tuple[Any, tuple[float, ...]]:
    """The seed's simulated hand holding the object at the seed's start pose (not opened),
    and that pose: what `simulate_hand` runs, `haptic emulate --object` puts on a bus and
    `hapticd` drives (its steps taking `step_duration_s` of real time)."""
    from sim_backend.hand import HandSimConfig, SimulatedHand  # chosen at run time

    start, world, world_rng = seeded_world(settings, parts)
    config = HandSimConfig(pose=start, grasp=settings.grasp, noise=settings.noise_spec,
                           fixed=settings.single_finger, step_duration_s=step_duration_s)
    return SimulatedHand(parts.hand, parts.contour, config, world_rng, world=world), start


def simulate_hand(settings: HandSettings, parts: HandParts | None = None, *,
                  on_step: Callable[[HandStepRecord], None] | None = None,
                  snapshot_steps: tuple[int, ...] = (),
                  backend_factory: Callable[[], Any] | None = None,
                  hidden: Any | None = None, keep_on_interrupt: bool = False
                  ) -> HandEpisodeReport:
    """Run one seeded hand episode on the simulated hand, or on the hand `backend_factory`
    makes (servos). Same settings, same report. With `keep_on_interrupt`, Ctrl-C or a stop
    signal ends it with what it had found (`runner.kept_on_interrupt`).

    `hidden` is the simulated hand behind an emulated bus, if any: the truth and the grasp's
    quality are read from it. Without it a run on servos knows the object's pose only while
    nothing turned it (the seed's start, where `haptic emulate` places it); once a
    manipulation has moved the object, the run is not scored (`truth_known` False)."""
    parts = parts or load_parts(settings)
    loc_rng = streams(settings.seed)[2]
    if backend_factory is None:
        sim, start = simulated_hand(settings, parts)
        hand = world = sim
    else:
        start = seeded_world(settings, parts)[0]
        hand, world = backend_factory(), hidden
    localizer = build_localizer(settings, parts, loc_rng)
    snapshots: dict[int, Hypotheses] = {}

    def record(step: HandStepRecord) -> None:
        if step.index in snapshot_steps:
            snapshots[step.index] = localizer.hypotheses(limit=SNAPSHOT_LIMIT)
        if on_step:
            on_step(step)

    unknown_quality = settings.single_finger or world is None  # clamped: no grasp to judge
    hand.open()
    try:
        hand.set_torque(True)
        start_quality = world.quality if world is not None else float("nan")
        result = run_hand_episode(hand, localizer, build_policy(settings), parts, settings,
                                  on_step=record,
                                  truth=None if world is None else lambda: world.pose,
                                  quality=None if unknown_quality else lambda: (
                                      world.quality, world.step_min_quality),
                                  keep_on_interrupt=keep_on_interrupt)
        if 0 in snapshot_steps and result.interrupted is None:
            snapshots.setdefault(0, localizer.hypotheses(limit=SNAPSHOT_LIMIT))
    finally:
        hand.close()
    truth = world.pose if world is not None else start
    known = world is not None or not any(s.kind == "manipulate" for s in result.steps)
    return HandEpisodeReport(settings=settings, start=start, truth=truth, result=result,
                             score=score(result.estimate, truth, result.dropped) if known
                             else HandScore(None, None, False, False),
                             parts=parts,
                             min_quality=float("nan") if unknown_quality else world.min_quality,
                             start_quality=float("nan") if unknown_quality else start_quality,
                             snapshots=snapshots, truth_known=known)
