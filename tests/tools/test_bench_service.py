"""B4 runs end to end when short (speed targets belong to the benchmark, not here)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tools import bench_service


def test_short_b4_reports_every_figure(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    bench_service.add_arguments(parser)
    out = tmp_path / "b4.json"
    args = parser.parse_args(["--duration", "1", "--subscribers", "3", "--json", str(out)])
    assert bench_service.run(args) == 0
    runs = json.loads(out.read_text())["runs"]
    assert [r["subscribers"] for r in runs] == [0, 3]
    for r in runs:
        assert r["ticks"] > 50 and r["period_ms"]["p50"] > 0
        assert r["command_rtt_ms"]["p99"] is not None and r["commands_timed"] > 5
        assert r["published"]["state"] > 50 and r["episodes_started"] >= 1
    assert runs[1]["reader_received"]["min"] > 50
