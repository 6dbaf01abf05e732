"""The loop's explorer, with its localizer in the compute process, takes exactly the steps
the offline episode runner takes; the compute process survives what the loop throws at it."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import asdict

import numpy as np
import pytest

from firmware_if.backend import HandCommand
from service.daemon.explorer import ComputeError, Explorer, Phase
from service.daemon.finger_compute import estimate_fields
from service.daemon.worker_link import WorkerDied, WorkerLink
from service.episode.runner import run_episode
from service.episode.scenario import (
    RunSettings,
    build_localizer,
    build_policy,
    draw_truth,
    episode_streams,
    surface_for,
)
from service.wire.envelope import Message
from sim_backend.finger import SimConfig, SimulatedFinger


@pytest.fixture(scope="module")
def link() -> Iterator[WorkerLink]:
    link = WorkerLink()
    link.start()
    yield link
    link.close()


def finger(settings: RunSettings, surface, seed: int, step_s: float = 0.0) -> SimulatedFinger:
    truth = draw_truth(settings, surface.map, np.random.default_rng(seed))
    f = SimulatedFinger(surface.map, SimConfig(start=truth.as_tuple(), radius=settings.radius,
                                               noise=settings.noise_spec,
                                               step_duration_s=step_s),
                        np.random.default_rng(seed + 1))
    f.open()
    f.set_torque(True)
    return f


def reply(link: WorkerLink, kind: str, timeout_s: float = 60.0) -> dict:
    """The next reply (of `kind`) from the compute process."""
    for msg in link.poll(timeout_s):
        assert msg.type == kind, msg.body
        return msg.body
    raise AssertionError(f"no {kind} within {timeout_s} s")


def configure(link: WorkerLink, settings: RunSettings) -> None:
    link.send("setup", settings=asdict(settings), backend="sim", cloud_points=50)
    assert reply(link, "ready")["truth"] is not None
    link.send("commit")


@pytest.mark.parametrize(("noise", "step_s"), [(False, 0.0), (True, 0.0), (False, 0.2)])
def test_exploration_matches_run_episode(link: WorkerLink, noise: bool, step_s: float) -> None:
    """With instant steps each update first finishes the localizer's work between steps
    (`Localizer.background`); with steps of 0.2 s that work is done while the move is under
    way. Either way the episode is `run_episode`'s."""
    settings = RunSettings(noise=noise, max_steps=40)
    surface = surface_for(settings)
    _, _, loc_rng, policy_rng = episode_streams(settings.seed)  # the first episode's
    reference = run_episode(finger(settings, surface, 3), build_localizer(settings, surface,
                            loc_rng), build_policy(settings), surface=surface,
                            step_length=settings.step, max_steps=settings.max_steps,
                            rng=policy_rng, walls=settings.walls)
    configure(link, settings)
    f = finger(settings, surface, 3, step_s)
    explorer = Explorer(link, settings)
    commands: list[HandCommand] = []

    def command(step: HandCommand) -> None:
        commands.append(step)
        f.command_hand(step)

    explorer.start(f.read_hand())
    while explorer.phase is not Phase.IDLE:
        waiting = explorer.phase in (Phase.DECIDE, Phase.UPDATING) and not explorer.paused
        explorer.tick(f.read_hand(), command, link.poll(60.0 if waiting else 0.0))
    assert [(c.moves[0].dx, c.moves[0].dy) for c in commands] == [
        s.command for s in reference.steps]
    assert explorer.estimate == estimate_fields(reference.estimate)
    assert explorer.steps == len(reference.steps)


def test_pause_holds_and_nothing_is_commanded(link: WorkerLink) -> None:
    settings = RunSettings()
    configure(link, settings)
    surface = surface_for(settings)
    f = finger(settings, surface, 1)
    explorer = Explorer(link, settings)
    explorer.start(f.read_hand())
    explorer.paused = True
    sent: list[HandCommand] = []
    out = explorer.tick(f.read_hand(), sent.append, link.poll(60.0))
    assert out.started  # the first belief arrived, and with it a move, held back
    for _ in range(20):
        explorer.tick(f.read_hand(), sent.append, link.poll())
    assert sent == [] and explorer.phase is Phase.DECIDE
    explorer.stop()


def test_a_move_held_back_by_a_pause_dies_with_its_episode(link: WorkerLink) -> None:
    """The finger held (a lost lease), the holder stopped and started again: the old
    episode's pending move must not be commanded before the new episode's first belief (it
    was, and the new belief's move then met a step under way: a fault)."""
    settings = RunSettings()
    configure(link, settings)
    f = finger(settings, surface_for(settings), 1)
    explorer = Explorer(link, settings)
    explorer.start(f.read_hand())
    explorer.paused = True
    sent: list[HandCommand] = []
    assert explorer.tick(f.read_hand(), sent.append, link.poll(60.0)).started
    explorer.stop()
    explorer.start(f.read_hand())
    out = explorer.tick(f.read_hand(), sent.append, [])
    assert sent == [] and not out.started  # nothing until the new belief
    while not out.started:
        out = explorer.tick(f.read_hand(), sent.append, link.poll(60.0))
    assert len(sent) == 1 and explorer.phase is Phase.STEPPING
    explorer.stop()


def test_a_hold_starts_no_new_episode_when_the_step_under_way_ends_one(
        link: WorkerLink) -> None:
    """With `repeat`, the lease lost during a step: the step completes and ends its episode
    (one step allowed). The hold must not begin the next episode (a held-out client saw
    `episode_started` during a hold, and its `episode_done` as "deactivated" at the end),
    and stopping then reports nothing under way."""
    settings = RunSettings(max_steps=1)
    configure(link, settings)
    f = finger(settings, surface_for(settings), 1)
    explorer = Explorer(link, settings)
    explorer.start(f.read_hand(), repeat=True)
    while explorer.phase is not Phase.STEPPING:
        explorer.tick(f.read_hand(), f.command_hand, link.poll(60.0))
    explorer.paused = True  # the lease ends while the step is under way
    while explorer.phase is not Phase.RESTART:
        explorer.tick(f.read_hand(), f.command_hand, link.poll(1.0))
    episode = explorer.episode
    for _ in range(5):
        out = explorer.tick(f.read_hand(), f.command_hand, link.poll(0.0))
        assert not out.started and not out.events
    assert explorer.phase is Phase.RESTART and explorer.episode == episode
    assert explorer.stop() is None and explorer.phase is Phase.IDLE


@pytest.fixture
def own_link() -> Iterator[WorkerLink]:
    """A compute process of the test's own: a cut episode's late replies stay in it."""
    link = WorkerLink()
    link.start()
    yield link
    link.close()


def one_step_episode(link: WorkerLink, *, repeat: bool) -> tuple[Explorer, SimulatedFinger]:
    """An explorer whose one-step episode has ended (`repeat`: the next not yet begun)."""
    settings = RunSettings(max_steps=1)
    configure(link, settings)
    f = finger(settings, surface_for(settings), 1)
    explorer = Explorer(link, settings)
    explorer.start(f.read_hand(), repeat=repeat)
    while explorer.phase is not (Phase.RESTART if repeat else Phase.IDLE):
        explorer.tick(f.read_hand(), f.command_hand, link.poll(1.0))
    return explorer, f


def test_an_episode_cut_before_its_first_belief_leaves_no_trace(own_link: WorkerLink) -> None:
    """A fault just as an episode starts (its start refused): `episode_done` went out for an
    episode that never began, its id was used up and the last estimate wiped."""
    explorer, f = one_step_episode(own_link, repeat=False)
    kept, episode = explorer.estimate, explorer.episode
    assert kept is not None
    explorer.start(f.read_hand())
    assert explorer.estimate is None and explorer.episode == episode + 1
    assert explorer.stop("fault") is None  # no episode_done
    assert explorer.episode == episode and explorer.estimate == kept
    assert explorer.estimate_fields()["episode"] == episode


def test_a_start_the_compute_process_refuses_leaves_no_trace(own_link: WorkerLink) -> None:
    """Its error reply left the new episode's id used and the estimate wiped (a review)."""
    explorer, f = one_step_episode(own_link, repeat=False)
    kept, episode = explorer.estimate, explorer.episode
    explorer.start(f.read_hand())
    refusal = Message(type="error", seq=1, t_mono_ns=0, t_wall_ns=0,
                      body={"req": explorer._req, "code": "bad", "message": "refused"})
    with pytest.raises(ComputeError, match="refused"):
        explorer.tick(f.read_hand(), f.command_hand, [refusal])
    assert explorer.episode == episode and explorer.estimate == kept
    assert explorer.phase is Phase.IDLE and explorer.stop("fault") is None


def test_repeat_begins_nothing_once_the_object_is_dropped(own_link: WorkerLink) -> None:
    """With `repeat`, a drop ended one episode and began the next, which ended at once,
    242 times in 5 s."""
    explorer, f = one_step_episode(own_link, repeat=True)
    episode = explorer.episode
    dropped = dataclasses.replace(f.read_hand(), dropped=True)
    out = explorer.tick(dropped, f.command_hand, [])
    assert explorer.phase is Phase.IDLE and not explorer.repeat and not out.events
    assert explorer.episode == episode


def test_a_refused_setup_leaves_the_current_scenario(link: WorkerLink) -> None:
    configure(link, RunSettings())
    link.send("setup", settings=asdict(RunSettings(map="/etc/hostname.txt", spacing=0.001)),
              backend="sim", cloud_points=50)
    error = reply(link, "error")
    assert error["code"] == "bad_config"
    # a file's content, and whether it exists, are not the client's business
    assert "missing, unreadable or not a grid" in error["message"]
    link.send("discard")
    link.send("start", truth=None, reading={"t_ns": 0, "dropped": False, "fingers": [
        {"centre": [0.0, 0.0, 0.0], "joints": [], "blocked": False}]})
    assert reply(link, "belief")["estimate"]["candidates"] > 0  # still the peaks scenario


def test_a_killed_compute_process_is_reported_and_replaced() -> None:
    link = WorkerLink()
    link.start()
    try:
        link.kill()
        with pytest.raises(WorkerDied):
            link.poll(1.0)
        assert not link.alive
        link.start()
        configure(link, RunSettings())
    finally:
        link.close()
