"""The compute process's half of a finger's episode on a map: what `run_episode` does
between two steps, one request at a time (`service.daemon.worker` serves the requests).

A finger is a hand of one: the loop sends the hand's reading and commands the
`HandCommand` (one `FingerMove`) chosen here. The localizer's update runs in slices, so a
new request cuts it short.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from service.daemon.quiet_files import is_map_file, quiet_file_error
from service.errors import MapError

SLICE_S = 0.02
"""Longest localizer slice between looks at the pipe."""


@dataclass
class FingerScenario:
    """One configured scenario: settings, the localizer's surface, the seeded streams."""

    settings: Any
    surface: Any
    loc_rng: np.random.Generator
    policy_rng: np.random.Generator
    first: bool = True
    """The next episode is the first after configure: it uses `haptic run`'s streams."""

    def streams(self) -> tuple[np.random.Generator, np.random.Generator]:
        """The next episode's localizer and policy streams: the first as `haptic run` seeds
        it; later episodes spawn fresh ones."""
        if self.first:
            loc_rng, policy_rng = self.loc_rng, self.policy_rng
            self.loc_rng = self.loc_rng.spawn(1)[0]
            self.first = False
            return loc_rng, policy_rng
        loc_rng, policy_rng = self.loc_rng.spawn(2)
        return loc_rng, policy_rng

    def episode(self, truth: Any, cloud_points: int) -> FingerEpisode:
        return FingerEpisode(self, *self.streams(), truth, cloud_points)


def setup(fields: dict[str, Any], backend: str, files: list[Path]
          ) -> tuple[FingerScenario, dict[str, Any]]:
    """The scenario of `fields` (RunSettings), checked whole, and the `ready` reply: the
    simulator's hidden start and world (its arrays in `files`, for the loop to map), and the
    map check's warnings (heights that look like millimetres, symmetries), which `haptic
    run` prints and a client is told too."""
    from service.episode.scenario import (
        RunSettings,
        draw_truth,
        episode_streams,
        for_backend,
        prepare_localizers,
        surface_for,
    )
    from service.localization.maps import check_map_spec, load_map

    settings = for_backend(RunSettings(**fields), backend)
    check_map_spec(settings.map, settings.spacing)  # the client's own mistake: told in full
    try:
        height_map = load_map(settings.map, settings.spacing)
    except MapError as exc:
        if not is_map_file(settings.map):
            raise  # a preset: its error says nothing about files
        raise quiet_file_error("map", settings.map, exc, "a grid of heights in metres",
                               MapError) from None
    surface = surface_for(settings, height_map)  # a radius it cannot take: told in full
    truth_rng, world_rng, loc_rng, policy_rng = episode_streams(settings.seed)
    prepare_localizers()
    scenario = FingerScenario(settings, surface, loc_rng, policy_rng)
    _build(scenario, scenario.loc_rng)  # options and map checked now, not later
    truth, world = None, None
    if backend == "sim":
        truth = draw_truth(settings, surface.map, truth_rng).as_tuple()
        world = _world(settings, surface, world_rng, files)
    from service.localization.map_check import check_map

    warnings = check_map(surface.map, settings.radius, settings.step).warnings
    return scenario, {"truth": None if truth is None else list(truth), "world": world,
                      "warnings": list(warnings)}


def _world(settings: Any, surface: Any, rng: np.random.Generator, files: list[Path]
           ) -> dict[str, Any]:
    """The simulated world (the map as the finger really meets it, perturbed by B2's
    noise), built here and handed over as two memory-mapped arrays, with the state of
    the world's random stream after the perturbation, so the loop's simulated finger
    behaves as `haptic run`'s does."""
    from service.localization.surface import contact_surface
    from sim_backend.world import perturbed

    noise = settings.noise_spec
    world = perturbed(surface.map, noise.surface_sigma, noise.surface_correlation, rng)
    centre = contact_surface(world, settings.radius).centre_heights
    folder = Path(os.environ.get("HAPTIC_SHM", "/dev/shm"))
    if not folder.is_dir():
        folder = Path(tempfile.gettempdir())
    paths = {}
    for name, array in (("heights", world.heights), ("centre", centre)):
        fd, path = tempfile.mkstemp(prefix=f"hapticd-{name}-", suffix=".npy", dir=folder)
        with os.fdopen(fd, "wb") as f:
            np.save(f, np.asarray(array), allow_pickle=False)
        paths[name] = path
        files.append(Path(path))
    return {"paths": paths, "spacing": world.spacing, "name": world.name,
            "rng": json.dumps(rng.bit_generator.state)}


def _build(scenario: FingerScenario, loc_rng: np.random.Generator) -> tuple[Any, Any]:
    from service.episode.scenario import build_localizer, build_policy

    return (build_localizer(scenario.settings, scenario.surface, loc_rng),
            build_policy(scenario.settings))


class FingerEpisode:
    """One episode of a finger on a map: its localizer, policy and what the loop's steps
    have shown so far (the displacement from the first contact, the moves found blocked)."""

    def __init__(self, sc: FingerScenario, loc_rng: np.random.Generator,
                 policy_rng: np.random.Generator, truth: Any, cloud_points: int) -> None:
        self.sc = sc
        self.localizer, self.policy = _build(sc, loc_rng)
        self.policy_rng = policy_rng
        self.truth = None if truth is None else tuple(truth)
        self.cloud_points = cloud_points
        self.origin = np.zeros(3)
        self.displacement = np.zeros(3)
        self.move = -1
        self.blocked = False
        self.blocked_here: set[int] = set()
        self.policy_ms = 0.0
        """The policy's time for the move under way (reported with its step)."""
        self.background_ms = 0.0
        """The localizer's background work while the previous move was under way (reported
        with the step that move ends in)."""
        self.settle_ms = 0.0
        """The background finished after the last reading, before the next move (`settle`)."""

    def start(self, body: dict[str, Any]) -> dict[str, Any]:
        """The first contact: the belief, and the first move."""
        from service.localization.localizers.base import Measurement

        reading = body["reading"]
        self.origin = np.asarray(reading["fingers"][0]["centre"], dtype=np.float64)
        t0 = time.monotonic_ns()
        self.localizer.start(Measurement(step=0, displacement=np.zeros(3),
                                         t_ns=int(reading["t_ns"])))
        return self._belief(0, (time.monotonic_ns() - t0) / 1e6)

    def update(self, body: dict[str, Any], interrupted: Callable[[], bool]
               ) -> dict[str, Any] | None:
        """Step `step` done: take its reading in, choose the next move (None: cut short)."""
        from service.localization.localizers.base import Budget, Measurement
        from service.localization.policies.base import MOVES

        if not self._finish_background(interrupted):
            return None
        step, reading = int(body["step"]), body["reading"]
        finger = reading["fingers"][0]
        self.displacement = np.asarray(finger["centre"], dtype=np.float64) - self.origin
        self.blocked = bool(finger["blocked"])
        if self.blocked:
            self.blocked_here.add(self.move)
        else:
            self.blocked_here.clear()
        command = MOVES[self.move] * self.sc.settings.step
        measurement = Measurement(step=step, blocked=self.blocked,
                                  displacement=self.displacement.copy(),
                                  t_ns=int(reading["t_ns"]),
                                  command=(float(command[0]), float(command[1])))
        t0 = time.monotonic_ns()
        self.localizer.begin_update(measurement)
        while not self.localizer.work(Budget.seconds(SLICE_S)):
            if interrupted():
                return None
        update_ms = (time.monotonic_ns() - t0) / 1e6
        self.settle_ms = 0.0
        if self.localizer.estimate().pending:  # as `settle`: before the move it would cost
            t1 = time.monotonic_ns()
            if not self._finish_background(interrupted, count=False):
                return None
            self.settle_ms = (time.monotonic_ns() - t1) / 1e6
        return self._belief(step, update_ms)

    def between_steps(self, interrupted: Callable[[], bool]) -> None:
        """While the move just chosen is under way: the localizer's background share
        (`Localizer.background`), until done or a request arrives; the next update
        finishes it first, so the outcome is `run_episode`'s however long the move takes."""
        self._finish_background(interrupted)

    def _finish_background(self, interrupted: Callable[[], bool], count: bool = True) -> bool:
        """Run the background share to its end; False if a request cut it short. `count`:
        its time is the move's `background_ms` (not a settle's)."""
        from service.localization.localizers.base import Budget

        t0 = time.monotonic_ns()
        try:
            while not self.localizer.background(Budget.seconds(SLICE_S)):
                if interrupted():
                    return False
            return True
        finally:
            if count:
                self.background_ms += (time.monotonic_ns() - t0) / 1e6

    def _belief(self, step: int, update_ms: float) -> dict[str, Any]:
        """The estimate, a cloud of the same moment, what happened (the step, the end) and,
        if the episode goes on, the policy's next move."""
        from service.localization.policies.base import MOVES, PolicyInput

        sc = self.sc
        est = self.localizer.estimate()
        hyp = self.localizer.hypotheses(limit=self.cloud_points)
        fields = estimate_fields(est)
        events: list[tuple[str, dict[str, Any]]] = []
        if step > 0:
            command = MOVES[self.move] * sc.settings.step
            events.append(("step", {
                "index": step, "move": self.move,
                "command": [float(command[0]), float(command[1])],
                "measurement": [float(v) for v in self.displacement],
                "blocked": self.blocked, "candidates": fields["candidates"],
                "compute_ms": update_ms, "policy_ms": self.policy_ms,
                "background_ms": self.background_ms, "settle_ms": self.settle_ms,
                "estimate": fields["pose"],
                **{k: fields[k] for k in ("position_sd", "heading_sd", "mode_mass")}}))
            self.background_ms = 0.0
        reason = ("converged" if est.converged else "eliminated" if est.candidates == 0
                  else "out_of_steps" if step >= sc.settings.max_steps else None)
        command = None
        if reason is None:
            t1 = time.perf_counter()
            view = PolicyInput(hypotheses=self.localizer.hypotheses(),
                               displacement=self.displacement[:2].copy(),
                               blocked=frozenset(self.blocked_here), surface=sc.surface,
                               step_length=sc.settings.step, rng=self.policy_rng,
                               walls=sc.settings.walls, estimate=est,
                               planar=sc.settings.planar)
            self.move = int(self.policy.next_move(view))
            self.policy_ms = (time.perf_counter() - t1) * 1e3
            dx, dy = MOVES[self.move] * sc.settings.step
            command = [[float(dx), float(dy), 0.0, 0.0]]
        else:
            events.append(("episode_done", {
                **fields, "steps": step, "reason": reason,
                "true_pose_eliminated": self._truth_eliminated()}))
        return {"estimate": fields, "update_ms": update_ms, "events": events,
                "done": reason is not None, "command": command,
                "topic": {"kind": "finger", "step": step,
                          "displacement": [float(v) for v in self.displacement]},
                "poses": hyp.poses.astype(np.float32), "weights": hyp.weights.astype(np.float32)}

    def _truth_eliminated(self) -> bool | None:
        """Whether a discrete localizer dropped the simulator's true pose (None elsewhere)."""
        retains = getattr(self.localizer, "retains", None)
        if retains is None or self.truth is None:
            return None
        kept = retains(self.truth, 1e-6 * self.sc.settings.step, 1e-6)
        return None if kept is None else not kept


def estimate_fields(est: Any) -> dict[str, Any]:
    """An Estimate as plain numbers (None for nothing or not finite)."""

    def num(v: float | None) -> float | None:
        return float(v) if v is not None and np.isfinite(v) else None

    def pose(p: Any) -> list[float] | None:
        return None if p is None else [float(v) for v in p]

    return {"pose": pose(est.pose), "candidates": int(est.candidates),
            "converged": bool(est.converged), "position_sd": num(est.position_sd),
            "heading_sd": num(est.heading_sd), "mode_mass": num(est.mode_mass),
            "runner_up": pose(est.runner_up),
            "runner_up_mass": None if est.runner_up is None else num(est.runner_up_mass)}
