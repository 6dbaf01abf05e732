"""`haptic run --backend dynamixel` whose emulator dies mid-run: one line, status 2."""

from __future__ import annotations

import threading

import pytest

from firmware_if.hand import load_hand
from service.localization.maps import load_map
from sim_backend.emulator import ServoBus
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos
from tools.cli import main


def test_a_lost_port_mid_run_is_one_line_and_status_2(capsys) -> None:
    hand = load_hand("spatial")
    plant = FingerPlant(hand, load_map("peaks"), (0.1, 0.1, 0.5))
    bus = ServoBus(hand_bus_servos(hand, plant), plant=plant).start()
    status: list[int] = []
    run = threading.Thread(target=lambda: status.append(main(
        ["run", "--backend", "dynamixel", "--port", bus.port, "--hand", "spatial",
         "--noise", "--max-steps", "60", "--quiet"])), daemon=True)
    try:
        run.start()
        # mid-episode: opening and touching down take about 60 packets, a step 5 to 20
        assert bus.wait_until(lambda: bus.stats["rx_packets"] > 90, 60.0)
    finally:
        bus.stop()  # as if `haptic emulate` were killed
    run.join(60)
    assert status == [2]
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "serial port" in err and "Traceback" not in err, err


@pytest.mark.parametrize("argv", [
    ["run", "--backend", "dynamixel", "--hand", "planar", "--map", "profile:smooth:20"],
    ["run", "--backend", "dynamixel", "--hand", "three-finger", "--object", "keyed"],
])
def test_a_missing_port_is_refused_before_the_run_prints(argv, tmp_path, capsys) -> None:
    """A port that does not exist is told before the run's header, in one line."""
    assert main([*argv, "--port", str(tmp_path / "ttyUSB9")]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and "ttyUSB9" in captured.err
    assert "adapter plugged in" in captured.err
