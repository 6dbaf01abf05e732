"""`haptic bench hand-bus`: one instruction packet per tick for the whole hand, both read
paths, and a seeded episode run both ways."""

from __future__ import annotations

import json

from firmware_if.dxl_bus import TORQUE_CHECK_CYCLES
from tools.cli import main


def test_bench_hand_bus_reads_the_hand_in_one_packet_per_tick(tmp_path, capsys):
    out = tmp_path / "hand-bus.json"
    assert main(["bench", "hand-bus", "--ticks", "20", "--seeds", "1", "--max-steps", "1",
                 "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert [t["read"] for t in data["ticks"]] == ["fast sync read", "sync read"]
    for t in data["ticks"]:
        # one instruction packet per tick, and the check of torque once in 20 ticks (a servo
        # that restarted by itself); missed cycles (`failures`) are the host's load
        assert TORQUE_CHECK_CYCLES == 20
        assert t["servos"] == 6 and t["packets_per_tick"] == 1.05
    (episode,) = data["episodes"]
    assert episode["bus_errors"] == 0 and "dropped" not in (episode["sim"], episode["bus"])
    assert "same outcome in" in capsys.readouterr().out
