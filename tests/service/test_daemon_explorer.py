"""The sliced explorer takes exactly the steps the offline episode runner takes."""

from __future__ import annotations

import time

import numpy as np
import pytest

from firmware_if.backend import StepCommand
from service.daemon.explorer import Explorer, Phase
from service.episode.runner import run_episode
from service.episode.scenario import (
    RunSettings,
    build_localizer,
    build_policy,
    draw_truth,
    surface_for,
)
from sim_backend.finger import SimConfig, SimulatedFinger


def finger(settings: RunSettings, surface, seed: int) -> SimulatedFinger:
    truth = draw_truth(settings, surface.map, np.random.default_rng(seed))
    f = SimulatedFinger(surface.map, SimConfig(start=truth.as_tuple(), radius=settings.radius,
                                               noise=settings.noise_spec),
                        np.random.default_rng(seed + 1))
    f.open()
    f.set_torque(True)
    return f


@pytest.mark.parametrize("noise, offload", [(False, False), (True, False), (True, True)])
def test_sliced_exploration_matches_run_episode(noise: bool, offload: bool) -> None:
    settings = RunSettings(noise=noise, max_steps=40)
    surface = surface_for(settings)
    # Offline reference.
    loc_rng, policy_rng = np.random.default_rng(7).spawn(2)
    reference = run_episode(finger(settings, surface, 3), build_localizer(settings, surface,
                            loc_rng), build_policy(settings), surface=surface,
                            step_length=settings.step, max_steps=settings.max_steps,
                            rng=policy_rng, walls=settings.walls)
    # The same, one tick at a time: read, step, update and decide spread over ticks.
    f = finger(settings, surface, 3)
    explorer = Explorer(settings, surface, np.random.default_rng(7), offload=offload)
    commands: list[StepCommand] = []

    def command(step: StepCommand) -> None:
        commands.append(step)
        f.command_step(step)

    explorer.start(f.read_state())
    ticks = 0
    while explorer.phase is not Phase.IDLE and ticks < 10_000:
        explorer.tick(f.read_state(), command, time.monotonic_ns() + 10**9)
        explorer.wait_update(5.0)
        ticks += 1
    explorer.close()
    assert [(c.dx, c.dy) for c in commands] == [s.command for s in reference.steps]
    assert explorer.estimate == reference.estimate
    assert explorer.steps == len(reference.steps)


def test_pause_holds_and_nothing_is_commanded() -> None:
    settings = RunSettings()
    surface = surface_for(settings)
    f = finger(settings, surface, 1)
    explorer = Explorer(settings, surface, np.random.default_rng(0))
    explorer.start(f.read_state())
    explorer.paused = True
    sent: list[StepCommand] = []
    for _ in range(20):
        explorer.tick(f.read_state(), sent.append, time.monotonic_ns() + 10**9)
    assert sent == [] and explorer.phase is Phase.DECIDE
