"""The compute process's half of a hand's episode: what `run_hand_episode` does between two
steps, one request at a time, through the same `HandStepper`.

The loop sends the whole hand's reading after each step (and, from the simulator, the
object's hidden pose and the grasp's true quality, for the record only); here the object
localizer takes it in, in slices, and the grasp-gated policy chooses the next
`HandCommand` - a policy decision may take hundreds of milliseconds, which is why it is
here and not in a tick. The episode ends converged, out of candidates or steps, with the
object dropped, or with no safe move left (`stuck`: an honest "not yet").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware_if.backend import FingerState, HandState
from firmware_if.errors import HandConfigError
from service.daemon.finger_compute import SLICE_S, estimate_fields
from service.daemon.quiet_files import is_object_file, quiet_file_error, quiet_hand_error
from service.errors import ObjectError


@dataclass
class HandScenario:
    """One configured hand scenario: settings, the loaded object and hand, seeded streams."""

    settings: Any
    parts: Any
    loc_rng: np.random.Generator
    first: bool = True

    def episode(self, truth: Any, cloud_points: int) -> HandEpisode:
        if self.first:  # as `haptic run --object` seeds it; later episodes spawn fresh ones
            loc_rng, self.loc_rng = self.loc_rng, self.loc_rng.spawn(1)[0]
            self.first = False
        else:
            loc_rng = self.loc_rng.spawn(1)[0]
        return HandEpisode(self, loc_rng, cloud_points)


def setup(fields: dict[str, Any], backend: str) -> tuple[HandScenario, dict[str, Any]]:
    """The scenario of `fields` (HandSettings): the object and hand loaded and checked
    against each other, and the `ready` reply with the simulator's hidden start pose."""
    from service.episode.hand_episode import seeded_world
    from service.episode.hand_scenario import (
        HandSettings,
        hand_for_backend,
        load_parts,
        streams,
    )

    settings = hand_for_backend(HandSettings(**fields), backend)
    try:
        parts = load_parts(settings)
    except HandConfigError as exc:  # a hand file that does not load
        raise quiet_hand_error(settings.hand, exc, holding=True) from None
    except ObjectError as exc:
        if not is_object_file(settings.object):
            raise  # a preset: its error says nothing about files
        raise quiet_file_error("object", settings.object, exc, "an outline this hand can "
                               "hold (x,z rows in metres, closed, or a mesh the plane cuts)",
                               ObjectError, hint="; a file in millimetres needs "
                               "scenario.object_units = \"mm\"") from None
    loc_rng = streams(settings.seed)[2]
    truth = seeded_world(settings, parts)[0] if backend == "sim" else None
    return HandScenario(settings, parts, loc_rng), {
        "truth": None if truth is None else list(truth), "world": None}


def hand_state(reading: dict[str, Any]) -> HandState:
    """The loop's reading (`Explorer._reading`) as the contract's HandState."""
    t_ns = int(reading["t_ns"])
    return HandState(t_ns=t_ns, dropped=bool(reading["dropped"]), fingers=tuple(
        FingerState(t_ns=t_ns, centre=tuple(f["centre"]), blocked=bool(f["blocked"]),
                    joints=tuple(f["joints"])) for f in reading["fingers"]))


class HandEpisode:
    """One hand episode: a `HandStepper` and the decision whose step is under way."""

    def __init__(self, sc: HandScenario, loc_rng: np.random.Generator,
                 cloud_points: int) -> None:
        from service.episode.hand_scenario import build_localizer, build_policy
        from service.episode.hand_step import HandStepper

        self.sc = sc
        self.stepper = HandStepper(build_localizer(sc.settings, sc.parts, loc_rng),
                                   build_policy(sc.settings), sc.parts, sc.settings)
        self.cloud_points = cloud_points
        self.decision: Any = None

    def start(self, body: dict[str, Any]) -> dict[str, Any]:
        state = hand_state(body["reading"])
        t0 = time.monotonic_ns()
        self.stepper.start(state)
        return self._belief(0, state, t0, [], body["reading"])

    def update(self, body: dict[str, Any], interrupted: Callable[[], bool]
               ) -> dict[str, Any] | None:
        """Step `step` done: take the hand's reading in, choose the next move (None: cut
        short by a newer request)."""
        from service.episode.hand_step import step_json
        from service.localization.localizers.base import Budget

        step, reading = int(body["step"]), body["reading"]
        state = hand_state(reading)
        stepper, localizer = self.stepper, self.stepper.localizer
        t0 = time.monotonic_ns()
        measurement = stepper.observe(step, self.decision, state)
        if measurement is not None:
            localizer.begin_update(measurement)
            while not localizer.work(Budget.seconds(SLICE_S)):
                if interrupted():
                    return None
            stepper.updated()
        compute_ms = (time.monotonic_ns() - t0) / 1e6
        settle_ms = stepper.confirm() if measurement is not None else 0.0
        quality, least = reading.get("quality"), reading.get("least_quality")
        record = stepper.record(step, self.decision, state, compute_ms=compute_ms,
                                settle_ms=settle_ms,
                                quality=float("nan") if quality is None else float(quality),
                                least_quality=float("nan") if least is None else float(least),
                                truth=reading.get("truth"))
        events = [("step", step_json(record))]
        if state.dropped:
            events.append(("dropped", {"step": step, "quality": quality}))
        return self._belief(step, state, t0, events, reading)

    def between_steps(self, interrupted: Callable[[], bool]) -> None:
        """A held object's localizers leave no work between steps."""

    def _belief(self, step: int, state: HandState, t0: int,
                events: list[tuple[str, dict[str, Any]]], reading: dict[str, Any]
                ) -> dict[str, Any]:
        """The estimate, a cloud of the same moment, what happened and, if the episode
        goes on, the next HandCommand."""
        from service.episode.hand_step import json_number

        stepper = self.stepper
        update_ms = (time.monotonic_ns() - t0) / 1e6
        est = stepper.estimate
        hyp = stepper.localizer.hypotheses(limit=self.cloud_points)
        fields = estimate_fields(est)
        predicted = None if self.decision is None else json_number(
            self.decision.predicted_quality)
        reason = ("dropped" if state.dropped else "converged" if est.converged
                  else "eliminated" if est.candidates == 0
                  else "out_of_steps" if step >= self.sc.settings.max_steps else None)
        command = None
        if reason is None:
            self.decision = stepper.decide(state)
            if self.decision.command is None:
                reason = "stuck"
            else:
                command = [None if m is None else [m.dx, m.dy, m.dz, m.roll]
                           for m in self.decision.command.moves]
        if reason is not None:
            events.append(("episode_done", {
                **fields, "steps": step, "reason": reason, "dropped": bool(state.dropped),
                "true_pose_eliminated": None}))
        return {"estimate": fields, "update_ms": update_ms, "events": events,
                "done": reason is not None, "command": command,
                "topic": {"kind": "hand", "step": step, "displacement": None,
                          "predicted_quality": predicted,
                          "quality": json_number(reading.get("quality"))},
                "poses": hyp.poses.astype(np.float32), "weights": hyp.weights.astype(np.float32)}
