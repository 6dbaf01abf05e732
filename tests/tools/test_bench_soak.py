"""The short soak of the reliability suite (issue 12): the daemon with subscriber processes
reconnecting and one stuck loses nothing and leaves no request unanswered. Timing targets
belong to `haptic bench soak --duration 600`, not here."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tools import bench_soak


def test_a_short_soak_has_no_gap_and_answers_everything(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    bench_soak.add_arguments(parser)
    out = tmp_path / "soak.json"
    args = parser.parse_args(["--duration", "5", "--subscribers", "4", "--reconnecting", "2",
                              "--reconnect-s", "1", "--floor-s", "0.5", "--json", str(out)])
    assert bench_soak.run(args) == 0
    r = json.loads(out.read_text())
    assert r["gaps"] == 0 and r["unanswered"] == 0 and r["subscribers_reporting"] == 4
    assert r["connections"] >= 1 + 2 * 4 + 1  # the reconnecting ones did reconnect
    assert r["received"]["reconnecting_min"] > 100 and r["received"]["steady"] > 500
    assert r["episodes"] >= 1 and r["ticks"] > 300 and r["periods_timed"] > 300
    assert r["rss"]["end_mb"] > 10
    assert r["loop_scheduling"]["policy"] in ("fifo", "other")
    assert 4.0 < r["empty_loop_floor"]["period_p50_ms"] < 6.0  # 200 Hz, nothing in the ticks


def test_memory_trend_reads_the_second_half() -> None:
    grows_then_flat = [(t, 100.0 + min(t, 50.0)) for t in range(0, 101, 1)]
    trend = bench_soak.memory_trend(grows_then_flat)
    assert trend["start_mb"] == 100.0 and trend["half_mb"] == 150.0
    assert abs(trend["second_half_mb_per_min"]) < 1e-9
    leaking = [(t, 100.0 + t / 60) for t in range(0, 121)]  # 1 MB a minute
    assert abs(bench_soak.memory_trend(leaking)["second_half_mb_per_min"] - 1.0) < 1e-6
