"""`haptic bench grasp` (B6): the summary keys the issue fixes, the ablation and a figure."""

from __future__ import annotations

import json

from tools.cli import main


def test_bench_grasp_writes_its_summary_and_figure(tmp_path, capsys):
    out, fig = tmp_path / "b6.json", tmp_path / "b6.png"
    assert main(["bench", "grasp", "--runs", "1", "--first-seed", "3", "--objects", "blob",
                 "--hands", "three-finger", "--max-steps", "15", "--json", str(out),
                 "--plot", str(fig)]) == 0
    assert "without the gate" in capsys.readouterr().out
    result = json.loads(out.read_text())
    summary = result["summary"]
    for key in ("runs", "successes", "wrong_declarations", "drops", "steps_median",
                "quality_min", "compute_ms_after_first_p99", "ablation_drops"):
        assert key in summary
    assert summary["runs"] == 1 and summary["drops"] == 0 and summary["wrong_declarations"] == 0
    assert set(result["table"]) == {"three-finger/blob/gated", "three-finger/blob/ablation",
                                    "three-finger/blob/single"}
    assert fig.stat().st_size > 10_000


def test_bench_grasp_refuses_an_unknown_family(capsys):
    assert main(["bench", "grasp", "--objects", "cube"]) == 2
    assert "unknown family 'cube'" in capsys.readouterr().err
