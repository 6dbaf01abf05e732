"""End to end through the Dynamixel backend on the servo-bus emulator (real dynamixel-sdk)."""

from __future__ import annotations

import numpy as np
import pytest

from service.daemon.harness import loopback_config, running_node
from service.registry import BACKENDS
from service.wire.client import Client, Subscriber

pytest.importorskip("sim_backend.emulator")
if "dynamixel" not in BACKENDS.names():
    pytest.skip("no dynamixel backend registered", allow_module_level=True)

from firmware_if.hand import load_hand  # noqa: E402
from service.localization.maps import load_map  # noqa: E402
from sim_backend.emulator import ServoBus  # noqa: E402
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos  # noqa: E402


def test_daemon_localizes_through_the_dynamixel_backend_on_the_emulator() -> None:
    hand = load_hand("spatial")
    truth = (0.10, 0.10, 2 * np.pi * 3 / 11)  # a pose-table entry, hidden in the plant
    plant = FingerPlant(hand, load_map("peaks"), truth)
    with ServoBus(hand_bus_servos(hand, plant), plant=plant) as bus:
        # noise = true: the sensor model tolerates the encoders' rounding (~0.1 mm).
        config = loopback_config({
            "backend": {"name": "dynamixel", "options": {
                "port": bus.port, "hand": "spatial",
                "cycle_budget_s": 0.05}},  # a busy test machine is slower than a bus
            "scenario": {"noise": True, "max_steps": 60}})
        with running_node(config) as node, \
                Subscriber(node.endpoints["pub"], ["estimate", "event", "state"]) as sub, \
                Client(node.endpoints["cmd"], timeout_s=5.0) as ctl:
            assert ctl.status()["backend"] == "dynamixel"
            assert sub.wait_for(lambda m: m.topic == "state" and m["fingers"], 10.0)
            ctl.call("activate")
            ctl.call("start_exploration")
            done = sub.wait_for(lambda m: m.topic == "event" and m["event"] in (
                "episode_done", "fault"), 60.0)
            assert done is not None and done["event"] == "episode_done", done
            assert done["converged"]
            # encoder rounding is noise: the refined pose is within a millimetre and a degree
            np.testing.assert_allclose(done["pose"][:2], truth[:2], atol=1e-3)
            turn = (done["pose"][2] - truth[2] + np.pi) % (2 * np.pi) - np.pi
            assert abs(turn) < np.deg2rad(1.0)
            ctl.call("deactivate")
