"""One hand episode's step logic, free of how steps are executed or timed.

`run_hand_episode` (a synchronous loop over any hand) and `hapticd`'s compute process (one
step per request, the localizer's update in slices) both go through a `HandStepper`: the
policy's view of the hand, which moves were blocked, what a step's readings tell the
localizer, and what the step's record holds. So the daemon's episode is the one `haptic
run --object` runs, step for step.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware_if.backend import HandState
from service.episode.hand_scenario import HandParts, HandSettings
from service.localization.localizers.base import Estimate, settle
from service.localization.localizers.object_base import HandMeasurement
from service.localization.policies.grasp_gated import GraspGatedPolicy, HandDecision, HandView

POLICY_HYPOTHESES = 500
"""Heaviest hypotheses the policy is shown."""


@dataclass(frozen=True)
class HandStepRecord:
    index: int
    kind: str
    """'explore' or 'manipulate'."""
    finger: int | None
    command: tuple[tuple[float, float, float] | None, ...]
    centres: tuple[tuple[float, float], ...]
    """Every fingertip centre read after the step (hand plane, metres)."""
    blocked: bool
    predicted_quality: float
    """Least quality the policy predicted over the plausible poses (newtons)."""
    quality: float
    """The grasp's true quality after the step (simulation only; NaN otherwise)."""
    least_quality: float
    """The least true quality during the step: a turn may dip far below where it ends
    (simulation only; NaN otherwise)."""
    candidates: int
    compute_ms: float
    policy_ms: float
    settle_ms: float
    """The whole-object check a declaration waited on, run after the update and before the
    next move (`HandStepper.confirm`); 0 when none waited."""
    estimate: tuple[float, float, float] | None
    truth: tuple[float, float, float] | None
    position_sd: float | None = None
    heading_sd: float | None = None
    mode_mass: float | None = None
    """The estimate's spread and its leading mode's share after the step, as a finger's
    step gives them (a hand's steps gave only a count of hypotheses)."""


def plane_centres(state: HandState) -> np.ndarray:
    """Every fingertip centre in the hand plane (x, z): (n, 2)."""
    return np.array([[f.centre[0], f.centre[2]] for f in state.fingers])


class HandStepper:
    """The localizer and policy of one episode, and what a step needs to remember: the
    moves found blocked from here and the latest estimate."""

    def __init__(self, localizer, policy: GraspGatedPolicy, parts: HandParts,
                 settings: HandSettings) -> None:
        self.localizer = localizer
        self.policy = policy
        self.parts = parts
        self.settings = settings
        self.blocked: set[tuple[int, int]] = set()
        self.estimate: Estimate | None = None
        self.policy_ms = 0.0
        self.sigma = float(localizer.ctx.sigma)

    def start(self, state: HandState) -> None:
        """The first contact: every finger's centre is evidence."""
        n = len(state.fingers)
        self.localizer.start(HandMeasurement(step=0, centres=plane_centres(state),
                                             moved=tuple(range(n))))
        self.estimate = self.localizer.estimate()

    @property
    def settled(self) -> bool:
        """The localizer has converged or has nothing left: no step would help."""
        return bool(self.estimate.converged or self.estimate.candidates == 0)

    def decide(self, state: HandState) -> HandDecision:
        """The policy's next move from the hand as it is (`command` None: no safe move)."""
        est = self.estimate
        t0 = time.perf_counter()
        view = HandView(hypotheses=self.localizer.hypotheses(limit=POLICY_HYPOTHESES),
                        centres=plane_centres(state),
                        joints=tuple(np.asarray(f.joints) for f in state.fingers),
                        field=self.parts.field, fingers=self.parts.hand.fingers,
                        torque=self.parts.torque, grasp=self.settings.grasp,
                        step_length=self.settings.step, sigma=self.sigma,
                        fixed=self.settings.single_finger, blocked=frozenset(self.blocked),
                        spread=(float(est.position_sd), float(est.heading_sd)),
                        mode_mass=float(est.mode_mass),
                        slope_sd=self.settings.noise_spec.surface_slope_sd,
                        motion=self.localizer.ctx.motion,
                        mismatch=(self.localizer.ctx.mismatch_sd,
                                  self.localizer.ctx.mismatch_length))
        decision = self.policy.decide(view)
        self.policy_ms = (time.perf_counter() - t0) * 1e3
        return decision

    def observe(self, index: int, decision: HandDecision, state: HandState
                ) -> HandMeasurement | None:
        """What the hand read after step `index` tells the localizer: None when the step
        was blocked or the object dropped (no new evidence). Remembers blocked moves."""
        moved_now = decision.command.moving
        if self.was_blocked(decision, state):
            if decision.finger is not None:
                self.blocked.add((decision.finger, decision.direction))
            return None
        self.blocked.clear()
        if state.dropped:
            return None
        n = len(state.fingers)
        manipulated = decision.kind == "manipulate"
        carried = None
        if manipulated:
            cmd = decision.command.moves
            carried = (np.array([[m.dx, m.dz] for m in cmd]), np.array([m.roll for m in cmd]))
        return HandMeasurement(step=index, centres=plane_centres(state),
                               moved=tuple(range(n)) if manipulated else moved_now,
                               carried=carried, t_ns=state.t_ns)

    @staticmethod
    def was_blocked(decision: HandDecision, state: HandState) -> bool:
        return any(state.fingers[i].blocked for i in decision.command.moving)

    def updated(self) -> None:
        """The localizer finished taking in a measurement."""
        self.estimate = self.localizer.estimate()

    def confirm(self) -> float:
        """Run the check a declaration waits on (`Estimate.pending`), if any, before the
        next move (`base.settle`), and judge the estimate again: the milliseconds it took,
        0 when none waited (the step's `settle_ms`)."""
        if not self.estimate.pending:
            return 0.0
        t0 = time.perf_counter()
        self.estimate = settle(self.localizer, self.estimate)
        return (time.perf_counter() - t0) * 1e3

    def record(self, index: int, decision: HandDecision, state: HandState, *,
               compute_ms: float, settle_ms: float = 0.0, quality: float = float("nan"),
               least_quality: float = float("nan"),
               truth: tuple[float, float, float] | None = None) -> HandStepRecord:
        return HandStepRecord(
            index=index, kind=decision.kind, finger=decision.finger,
            command=tuple(None if m is None else (m.dx, m.dz, m.roll)
                          for m in decision.command.moves),
            centres=tuple(map(tuple, plane_centres(state).tolist())),
            blocked=self.was_blocked(decision, state),
            predicted_quality=decision.predicted_quality, quality=quality,
            least_quality=least_quality, candidates=self.estimate.candidates, compute_ms=compute_ms,
            policy_ms=self.policy_ms, settle_ms=settle_ms, estimate=self.estimate.pose,
            truth=truth, position_sd=self.estimate.position_sd,
            heading_sd=self.estimate.heading_sd, mode_mass=self.estimate.mode_mass)


def json_number(v: float | None) -> float | None:
    """A number for JSON: None for nothing or not finite."""
    return None if v is None or not math.isfinite(v) else float(v)


def step_json(s: HandStepRecord) -> dict[str, Any]:
    """A step as `haptic run --object --json` records it (and `hapticd` streams it)."""
    return {"index": s.index, "kind": s.kind, "finger": s.finger,
            "command": [None if m is None else list(m) for m in s.command],
            "centres": [list(c) for c in s.centres], "blocked": s.blocked,
            "predicted_quality": json_number(s.predicted_quality),
            "quality": json_number(s.quality),
            "least_quality": json_number(s.least_quality),
            "candidates": s.candidates, "compute_ms": s.compute_ms, "policy_ms": s.policy_ms,
            "settle_ms": s.settle_ms,
            "estimate": None if s.estimate is None else list(s.estimate),
            "position_sd": json_number(s.position_sd), "heading_sd": json_number(s.heading_sd),
            "mode_mass": json_number(s.mode_mass),
            "truth": None if s.truth is None else list(s.truth)}
