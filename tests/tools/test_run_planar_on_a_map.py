"""`haptic run --backend dynamixel --hand planar` on a map: a planar chain steps only along
its plane, so the run asks for no sideways step (a held-out lab's planar finger on `peaks`
asked for 36 in 100 steps, every one blocked, and declared only at its 100th)."""

from __future__ import annotations

import json

from firmware_if.hand import load_hand
from service.localization.maps import load_map
from sim_backend.emulator import ServoBus
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos
from tools.cli import main


def test_a_planar_finger_on_a_map_steps_only_along_its_plane(tmp_path, capsys) -> None:
    hand = load_hand("planar")
    plant = FingerPlant(hand, load_map("peaks"), (0.12, 0.10, 0.571))
    out = tmp_path / "run.json"
    with ServoBus(hand_bus_servos(hand, plant), plant=plant) as bus:
        status = main(["run", "--backend", "dynamixel", "--port", bus.port, "--hand",
                       "planar", "--map", "peaks", "--max-steps", "8", "--quiet", "--json",
                       str(out)])
    assert status == 0, capsys.readouterr()
    steps = json.loads(out.read_text())["steps"]
    assert len(steps) == 8
    assert all(step["command"][1] == 0.0 and not step["blocked"] for step in steps), steps
