"""`haptic bench faults` end to end, one round (the must-show runs 20): the emulator
process is killed under hapticd, a fault latches, the daemon stays up and a reset onto a
new emulator at the same path recovers."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tools import bench_faults


def test_one_round_of_the_fault_campaign(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    bench_faults.add_arguments(parser)
    out = tmp_path / "faults.json"
    assert bench_faults.run(parser.parse_args(["--rounds", "1", "--json", str(out)])) == 0
    r = json.loads(out.read_text())
    (round_,) = r["each"]
    assert round_["passed"] and "serial port" in round_["reason"]
    assert r["daemon_alive"] and r["resets_ok"] == 1 and r["explores_after"]
