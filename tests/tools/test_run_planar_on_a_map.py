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


def _run_on_the_emulator(tmp_path, capsys, start: tuple[float, float, float],
                         max_steps: int) -> list[dict]:
    """The steps of `haptic run` with the planar hand on `peaks` through the emulated bus,
    the finger at `start` (x, y, heading)."""
    hand = load_hand("planar")
    plant = FingerPlant(hand, load_map("peaks"), start)
    out = tmp_path / "run.json"
    with ServoBus(hand_bus_servos(hand, plant), plant=plant) as bus:
        status = main(["run", "--backend", "dynamixel", "--port", bus.port, "--hand",
                       "planar", "--map", "peaks", "--max-steps", str(max_steps), "--quiet",
                       "--cycle-budget", "50",  # make test beside other work: load 11 faulted it
                       "--json", str(out)])
    assert status == 0, capsys.readouterr()
    return json.loads(out.read_text())["steps"]


def test_a_planar_finger_on_a_map_steps_only_along_its_plane(tmp_path, capsys) -> None:
    steps = _run_on_the_emulator(tmp_path, capsys, (0.12, 0.10, 0.571), 8)
    assert len(steps) == 8
    assert all(step["command"][1] == 0.0 and not step["blocked"] for step in steps), steps


def _longest_shuttle(moves: list[int]) -> int:
    """The most steps in a row that each undo the step before."""
    longest = run = 1
    for before, after in zip(moves, moves[1:], strict=False):
        run = run + 1 if {before, after} == {0, 2} and before != after else 1
        longest = max(longest, run)
    return longest


def test_a_planar_finger_at_its_workspace_limit_goes_on_to_unread_places(tmp_path,
                                                                        capsys) -> None:
    """The noticed defect: the places beyond a blocked step counted as out of reach only
    24 steps out, so the nearest "unread" place was the 25th, past the limit. A planar
    finger stopped by its workspace at +x (the emulator's seed 0) shuttled +x/-x between
    the last two places before the limit from step 41 on, with unread places 14 steps the
    other way. Now it walks to them."""
    steps = _run_on_the_emulator(tmp_path, capsys, (0.15, 0.17, 0.0), 50)
    assert any(step["blocked"] for step in steps)  # it met its limit
    moves = [0 if step["command"][0] > 0 else 2 for step in steps]
    assert _longest_shuttle(moves) < 4, moves
