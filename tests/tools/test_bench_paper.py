"""`haptic bench paper` (B1) on a few runs: JSON summary keys, figure, table."""

import json

from tools.cli import main

SUMMARY_KEYS = {"runs", "successes", "wrong_declarations", "steps_mean", "steps_sd",
                "steps_max", "true_pose_eliminated_runs", "first_step_elimination_mean",
                "first_step_elimination_max", "compute_ms_first_median", "compute_ms_median",
                "compute_ms_p99"}


def test_bench_paper_writes_summary_and_figure(tmp_path, capsys):
    out, png = tmp_path / "b1.json", tmp_path / "b1.png"
    assert main(["bench", "paper", "--runs", "6", "--json", str(out), "--plot", str(png),
                 "--algorithm", "elimination", "--policy", "paper"]) == 0
    summary = json.loads(out.read_text())["summary"]
    assert set(summary) >= SUMMARY_KEYS
    assert summary["runs"] == 6 and summary["successes"] == 6
    assert summary["true_pose_eliminated_runs"] == 0
    assert 0 < summary["first_step_elimination_mean"] < 1
    assert png.stat().st_size > 10_000
    printed = capsys.readouterr()
    assert "23.6 +/- 8.7" in printed.out and "6/6" in printed.out
    # not a terminal (a log, a pipe): progress as lines, the first and the last at least
    lines = [line.strip("\r") for line in printed.err.splitlines()]
    assert any(line.startswith("B1 elimination + paper: 0/6 runs") for line in lines)
    assert any(line.startswith("B1 elimination + paper: 6/6 runs") for line in lines)


def test_the_papers_figures_stand_only_beside_its_own_map(tmp_path, capsys):
    """A held-out researcher's own map was tabled beside the paper's `peaks` results
    ("103/103 (as reported)", "23.6 +/- 8.7") and its figure shaded the paper's band."""
    import numpy as np

    waves = np.add.outer(np.sin(np.arange(150) / 9.0), np.cos(np.arange(150) / 7.0))
    np.save(tmp_path / "own.npy", 0.004 * waves)
    assert main(["bench", "paper", "--runs", "2", "--map", str(tmp_path / "own.npy"),
                 "--spacing", "0.001", "--algorithm", "elimination", "--policy", "paper",
                 "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "successes" in printed and "/2 (wrong declarations" in printed
    assert "as reported" not in printed and "23.6" not in printed


def test_bench_rejects_zero_runs(capsys):
    assert main(["bench", "paper", "--runs", "0"]) == 2
    assert "--runs" in capsys.readouterr().err


def test_first_step_figure_is_the_share_of_the_pose_table_the_first_move_rules_out(tmp_path):
    out = tmp_path / "b1.json"
    assert main(["bench", "paper", "--runs", "4", "--json", str(out), "--algorithm",
                 "elimination", "--policy", "paper"]) == 0
    data = json.loads(out.read_text())
    own = [1 - r["steps"][0]["candidates"] / r["initial_candidates"] for r in data["runs"]]
    # for Algorithm III the figure is its own first-step count, as in the paper
    assert abs(data["summary"]["first_step_elimination_mean"] - sum(own) / len(own)) < 1e-12
    assert main(["bench", "paper", "--runs", "4", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    pool_cap = 1 - data["runs"][0]["steps"][0]["candidates"] / data["runs"][0][
        "initial_candidates"]
    assert data["summary"]["first_step_elimination_mean"] != pool_cap  # not 20,000 -> 1,000
    assert 0 < data["summary"]["first_step_elimination_mean"] < 0.9


def test_progress_shows_on_a_terminal_that_tells_no_size():
    """A held-out check under a bare pseudo-terminal (0 x 0, as `pty.fork` gives) saw no
    progress at all: tqdm cut each line to 0 columns and hid the bar below row 0."""
    import os
    import pty
    import subprocess
    import sys
    from pathlib import Path

    script = ("from tools.bench_common import progress\n"
              "with progress(3, 'B0 size') as bar:\n"
              "    bar.update(3)\n")
    leader, follower = pty.openpty()  # no size set: the terminal says 0 x 0
    try:
        assert os.get_terminal_size(follower).columns == 0
        proc = subprocess.run([sys.executable, "-c", script], stdin=follower, stdout=follower,
                              stderr=follower, cwd=Path(__file__).resolve().parents[2],
                              timeout=60)
        os.close(follower)
        follower = -1
        out = b""
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # the pty is drained once its other end is closed
                break
            if not chunk:
                break
            out += chunk
    finally:
        os.close(leader)
        if follower >= 0:
            os.close(follower)
    assert proc.returncode == 0
    assert b"B0 size:   0%" in out and b"0/3" in out, out
