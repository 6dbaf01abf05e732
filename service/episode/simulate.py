"""A whole simulated episode from settings: what `haptic run` and the benchmarks call."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_if.backend import Backend
from service.episode.runner import EpisodeResult, StepRecord, run_episode
from service.episode.scenario import (
    RunSettings,
    Score,
    Truth,
    build_localizer,
    build_policy,
    draw_truth,
    episode_streams,
    score,
    surface_for,
)
from service.localization.localizers.base import Hypotheses, Localizer
from service.localization.models import rotate
from service.localization.surface import HeightMap

SNAPSHOT_LIMIT = 4000
"""Most hypotheses kept per figure snapshot."""


@dataclass
class EpisodeReport:
    settings: RunSettings
    truth: Truth
    result: EpisodeResult
    score: Score
    true_pose_eliminated: bool | None
    height_map: HeightMap
    """The map the localizer used (for figures; not part of the JSON)."""
    snapshots: dict[int, Hypotheses] = field(default_factory=dict)
    """Hypotheses after the steps asked for (0 = before the first move), for figures."""

    def to_json(self) -> dict[str, Any]:
        est = self.result.estimate
        return {
            "settings": self.settings.to_json(),
            "truth": {"x": self.truth.x, "y": self.truth.y, "heading": self.truth.heading},
            "initial_candidates": self.result.initial_candidates,
            "steps": [_step_json(s) for s in self.result.steps],
            "estimate": None if est is None or est.pose is None else {
                "x": est.pose[0], "y": est.pose[1], "heading": est.pose[2],
                "candidates": est.candidates, "position_sd": _num(est.position_sd),
                "heading_sd": _num(est.heading_sd), "mode_mass": _num(est.mode_mass),
            },
            "converged": self.result.converged,
            "ended": self.result.ended,
            "fault": self.result.fault,
            "interrupted": self.result.interrupted,
            "success": self.score.success,
            "wrong_declaration": self.score.wrong_declaration,
            "position_error": self.score.position_error,
            "heading_error": self.score.heading_error,
            "true_pose_eliminated": self.true_pose_eliminated,
        }


def _num(v: float) -> float | None:
    return None if not np.isfinite(v) else float(v)


def _step_json(s: StepRecord) -> dict[str, Any]:
    return {"index": s.index, "move": s.move, "command": list(s.command),
            "measurement": list(s.measurement), "blocked": s.blocked,
            "candidates": s.candidates, "compute_ms": s.compute_ms, "policy_ms": s.policy_ms,
            "background_ms": s.background_ms, "settle_ms": s.settle_ms,
            "estimate": None if s.estimate is None else list(s.estimate),
            "position_sd": _num(s.position_sd), "heading_sd": _num(s.heading_sd),
            "mode_mass": _num(s.mode_mass)}


def simulate(settings: RunSettings, height_map: HeightMap | None = None, *,
             on_step: Callable[[StepRecord], None] | None = None,
             snapshot_steps: tuple[int, ...] = (),
             backend_factory: Callable[[Truth], Backend] | None = None,
             keep_on_interrupt: bool = False) -> EpisodeReport:
    """Run one seeded episode. Same settings, same report. With `keep_on_interrupt`, Ctrl-C
    or a stop signal ends it with what it had found (`runner.kept_on_interrupt`).

    The finger is simulated unless `backend_factory` gives another (a real or emulated
    hand); the truth is still drawn from the seed, for scoring.
    """
    surface = surface_for(settings, height_map)
    truth_rng, world_rng, loc_rng, policy_rng = episode_streams(settings.seed)
    truth = draw_truth(settings, surface.map, truth_rng)
    if backend_factory is None:
        finger = _sim_finger(settings, surface.map, truth, world_rng)
    else:
        finger = backend_factory(truth)
    localizer = build_localizer(settings, surface, loc_rng)
    snapshots: dict[int, Hypotheses] = {}

    def snapshot(index: int) -> None:
        if index in snapshot_steps:
            snapshots[index] = localizer.hypotheses(limit=SNAPSHOT_LIMIT)

    def record(step: StepRecord) -> None:
        snapshot(step.index)
        if on_step:
            on_step(step)

    finger.open()
    try:
        finger.set_torque(True)
        truth = _where_it_began(truth, finger)
        result = run_episode(finger, localizer, build_policy(settings), surface=surface,
                             step_length=settings.step, max_steps=settings.max_steps,
                             rng=policy_rng, walls=settings.walls,
                             planar=settings.planar, on_step=record,
                             on_start=lambda: snapshot(0),
                             keep_on_interrupt=keep_on_interrupt)
    finally:
        finger.close()
    if snapshot_steps and result.interrupted is None:  # the end too: a figure's last panel
        # shows the final belief (not a localizer cut in the middle of an update)
        snapshots[len(result.steps)] = localizer.hypotheses(limit=SNAPSHOT_LIMIT)
    return EpisodeReport(settings=settings, truth=truth, result=result, height_map=surface.map,
                         score=score(result.estimate, truth, settings.step),
                         # a localizer cut inside an update cannot say
                         true_pose_eliminated=None if result.interrupted is not None
                         else _truth_eliminated(localizer, truth, settings),
                         snapshots=snapshots)


def _where_it_began(truth: Truth, finger: Backend) -> Truth:
    """The seed's start moved to where the finger touched down: a finger on servos knows
    where its home posture puts the tip (`home_centre`), and a fresh `haptic emulate` puts
    the seed's start under it, turned by the seed's heading. A second run on the same
    emulator begins where the first ended, and was scored against the seed's start: a
    right pose reported "WRONG", 42 mm off (a held-out check). The simulator's finger
    begins at the truth itself."""
    home = getattr(finger, "home_centre", None)
    if home is None:
        return truth
    centre = np.asarray(finger.read_state().centre, dtype=np.float64)
    dx, dy = rotate(np.asarray(truth.heading), centre[0] - home[0], centre[1] - home[1])
    return Truth(truth.x + float(dx), truth.y + float(dy), truth.heading)


def _sim_finger(settings: RunSettings, height_map: HeightMap, truth: Truth,
                rng: np.random.Generator) -> Backend:
    from sim_backend.finger import SimConfig, SimulatedFinger  # chosen at run time, not import

    return SimulatedFinger(height_map, SimConfig(start=truth.as_tuple(), radius=settings.radius,
                                                 noise=settings.noise_spec), rng)


def _truth_eliminated(localizer: Localizer, truth: Truth, settings: RunSettings) -> bool | None:
    """Whether a discrete localizer dropped the true pose (None where that has no meaning)."""
    retains = getattr(localizer, "retains", None)
    if retains is None:
        return None
    kept = retains(truth.as_tuple(), 1e-6 * settings.step, 1e-6)
    return None if kept is None else not kept
