"""What the daemon streams is a faithful record: each cloud is one moment, each step is the
step `haptic run` records, episode ids never repeat."""

from __future__ import annotations

import time

import numpy as np
import pytest

from service.daemon.explorer import Explorer, Phase
from service.daemon.harness import loopback_config, running_node
from service.episode.scenario import RunSettings, draw_truth, surface_for
from service.episode.simulate import simulate
from service.wire.client import Client, Subscriber
from sim_backend.finger import SimConfig, SimulatedFinger


def test_every_cloud_is_one_moment_even_mid_update() -> None:
    """total, poses and weights of a cloud come from the same update (1 cloud in 70 once
    carried more poses than its total: a sample taken mid-update beside an older count)."""
    from dataclasses import asdict

    from service.daemon.worker_link import WorkerLink

    settings = RunSettings(noise=True, max_steps=12, seed=3)
    surface = surface_for(settings)
    truth = draw_truth(settings, surface.map, np.random.default_rng(3))
    f = SimulatedFinger(surface.map, SimConfig(start=truth.as_tuple(), radius=settings.radius,
                                               noise=settings.noise_spec),
                        np.random.default_rng(4))
    f.open()
    f.set_torque(True)
    link = WorkerLink()
    link.start()
    try:
        link.send("setup", settings=asdict(settings), backend="sim", cloud_points=500)
        assert link.poll(60.0)[0].type == "ready"
        link.send("commit")
        explorer = Explorer(link, settings)
        explorer.start(f.read_hand())
        count_after: dict[int, int] = {}
        clouds, mid_update = [], 0
        deadline = time.monotonic() + 120
        while explorer.phase is not Phase.IDLE and time.monotonic() < deadline:
            # a cloud is asked for in every tick, mid-update too
            out = explorer.tick(f.read_hand(), f.command_hand, link.poll(0.002))
            for name, fields in out.events:
                if name == "episode_started":
                    count_after[0] = fields["candidates"]
                if name == "step":
                    count_after[fields["index"]] = fields["candidates"]
            mid_update += explorer.phase is Phase.UPDATING
            cloud = explorer.cloud()
            if cloud is not None:
                clouds.append(cloud)
    finally:
        link.close()
    assert mid_update > 0 and len(clouds) > 20
    for cloud in clouds:
        assert cloud.total == count_after[cloud.step]
        assert len(cloud.hypotheses.poses) <= cloud.total
        assert np.isclose(cloud.hypotheses.weights.sum(), 1.0)


def strip_timings(steps: list[dict]) -> list[dict]:
    untimed = ("compute_ms", "policy_ms", "background_ms", "settle_ms", "episode", "event")
    return [{k: v for k, v in s.items() if k not in untimed} for s in steps]


def events_of_one_episode(node, timeout_s: float = 60.0) -> list[dict]:
    """Every event from starting an episode on `node` to its end."""
    events = []
    with Subscriber(node.endpoints["pub"], ["state"]) as states:  # the finger is read
        assert states.wait_for(lambda m: m["state"] == "inactive" and m["fingers"], 10)
    with Subscriber(node.endpoints["pub"], ["event"]) as sub, \
            Client(node.endpoints["cmd"]) as c:
        c.call("activate")
        c.call("start_exploration")
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            msg = sub.recv(1.0)
            c.call("acquire")
            if msg is None:
                continue
            events.append(msg.body)
            if msg["event"] == "episode_done":
                c.call("deactivate")
                c.call("release")
                return events
    raise AssertionError("the episode did not end")


@pytest.mark.parametrize("scenario", [
    {"seed": 4},
    {"seed": 2, "localizer": "elimination", "policy": "paper"},
])
def test_the_first_episode_is_haptic_runs_and_the_stream_says_every_step(scenario) -> None:
    config = loopback_config({"backend": {"step_duration_s": 0.0}, "scenario": scenario})
    with running_node(config) as node:
        events = events_of_one_episode(node)
    settings = config.run_settings()
    report = simulate(settings)
    expected = report.to_json()
    started = next(e for e in events if e["event"] == "episode_started")
    done = events[-1]
    steps = [e for e in events if e["event"] == "step"]
    assert started["settings"] == expected["settings"]
    assert started["candidates"] == expected["initial_candidates"]
    assert started["truth"] == pytest.approx(
        [expected["truth"][k] for k in ("x", "y", "heading")])
    assert strip_timings(steps) == strip_timings(expected["steps"])
    assert done["converged"] == expected["converged"] and done["reason"] == "converged"
    assert done["pose"] == [expected["estimate"][k] for k in ("x", "y", "heading")]
    assert done.get("true_pose_eliminated") == expected["true_pose_eliminated"]


def test_episode_ids_are_unique_across_configure() -> None:
    config = loopback_config({"backend": {"step_duration_s": 0.0}})
    with running_node(config) as node:
        first = events_of_one_episode(node)
        with Client(node.endpoints["cmd"]) as c:
            c.call("configure", changes={"scenario": {"seed": 5}})
            truth = c.call("status")["sim_truth"]
            c.call("release")
        second = events_of_one_episode(node)
    ids = [e["episode"] for e in first + second if e["event"] == "episode_started"]
    assert ids == [1, 2]
    assert next(e for e in second if e["event"] == "episode_started")["truth"] == truth
