"""`haptic campaign`: a grid of scenarios, resumable, on a local pool or a Dask cluster."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tools import campaign as campaign_module
from tools.cli import main

CAMPAIGN = """
name = "tiny"
runs = {runs}
[fixed]
noise = true
max_steps = 4
[grid]
algorithm = ["particles", "elimination"]
map = ["bumps:20:1"]
"""
TIMING_COLUMNS = ("compute_first_ms", "compute_after_first_median_ms",
                  "compute_after_first_p99_ms", "policy_median_ms", "workers")


def write(tmp_path, runs=2, name="c.toml"):
    path = tmp_path / name
    path.write_text(CAMPAIGN.format(runs=runs))
    return path


def episodes(folder):
    """The episode table without timings (and who ran it)."""
    with (folder / "episodes.csv").open() as f:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS}
                for row in csv.DictReader(f)]


def stored(folder):
    return [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]


def test_a_campaign_writes_a_table_a_summary_and_figures(tmp_path, capsys):
    assert main(["campaign", str(write(tmp_path)), "--workers", "1"]) == 0
    out = tmp_path / "c-results"
    rows = episodes(out)
    assert len(rows) == 4 and {r["algorithm"] for r in rows} == {"particles", "elimination"}
    assert {r["seed"] for r in rows} == {"0", "1"}
    summary = (out / "summary.md").read_text()
    assert "| algorithm=particles, map=bumps:20:1 | 2 |" in summary and "1 worker" in summary
    assert len(list((out / "figures").glob("*.png"))) == 2
    assert main(["campaign", str(write(tmp_path)), "--workers", "1"]) == 0
    assert "4 already done, 0 to run" in capsys.readouterr().out


def test_ctrl_c_keeps_finished_episodes_and_the_rerun_runs_only_the_rest(
        tmp_path, monkeypatch, capsys):
    real_append = campaign_module.Store.append
    calls = []

    def append_then_interrupt(self, record):
        real_append(self, record)
        calls.append(record)
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(campaign_module.Store, "append", append_then_interrupt)
    path = write(tmp_path, runs=2)
    assert main(["campaign", str(path), "--workers", "1"]) == 130
    out = tmp_path / "c-results"
    assert len(stored(out)) == 2 and "interrupted" in (out / "summary.md").read_text()
    monkeypatch.undo()
    capsys.readouterr()
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    assert "2 already done, 2 to run" in capsys.readouterr().out
    assert len(stored(out)) == 4


def test_a_killed_campaign_resumes_without_rerunning_finished_episodes(tmp_path, capsys):
    path = write(tmp_path, runs=4)
    store = tmp_path / "c-results" / "episodes.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "campaign", str(path),
                             "--workers", "1"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "MPLBACKEND": "Agg"})
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:  # wait for 3 episodes
        if store.exists() and store.read_text().count("\n") >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = stored(tmp_path / "c-results")
    assert 3 <= len(before) < 8, "the campaign finished before it could be killed"
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    assert f"{len(before)} already done, {8 - len(before)} to run" in capsys.readouterr().out
    after = stored(tmp_path / "c-results")
    assert after[:len(before)] == before and len(after) == 8
    assert len({(r["scenario"], r["seed"]) for r in after}) == 8


def test_a_dask_cluster_gives_the_local_pools_results(tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    path = write(tmp_path, runs=2)
    assert main(["campaign", str(path), "--workers", "2", "--out",
                 str(tmp_path / "pool")]) == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        assert main(["campaign", str(path), "--scheduler", cluster.scheduler_address,
                     "--out", str(tmp_path / "dask")]) == 0
    assert "Dask cluster at tcp://127.0.0.1" in capsys.readouterr().out
    assert episodes(tmp_path / "dask") == episodes(tmp_path / "pool")


@pytest.mark.parametrize("text, message", [
    ("runs = 2\n[grid]\nalgoritm = ['grid']\n", "did you mean 'algorithm'"),
    ("runs = 2\n[fixed]\nnoise = 'yes'\n", "noise must be true or false"),
    ("runs = 2\n[grid]\nradius = 0.008\n", "must be a non-empty list"),
    ("runs = 0\n", "runs must be a whole number >= 1"),
    ("runs = 2\ncolour = 1\n", "unknown key 'colour'"),
    ("runs = [\n", "not valid TOML"),
])
def test_bad_campaign_files_are_one_line_errors(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert main(["campaign", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_map_file_is_taken_from_the_campaign_files_folder(tmp_path, monkeypatch, capsys):
    """A researcher's findings: `haptic campaign camp/tiny.toml` looked for
    '../maps/bumps.npy' from the working folder, while its results went beside the file;
    and a campaign whose map failed to load left an empty results folder behind."""
    import numpy as np

    (tmp_path / "maps").mkdir()
    (tmp_path / "camp").mkdir()
    np.save(tmp_path / "maps" / "flat.npy", np.zeros((40, 40)))
    np.save(tmp_path / "maps" / "bad.npy", np.full((40, 40), np.nan))
    for name, map_file in (("tiny", "flat.npy"), ("broken", "bad.npy")):
        (tmp_path / "camp" / f"{name}.toml").write_text(
            f'runs = 1\n[fixed]\nmap = "../maps/{map_file}"\nspacing = 0.005\nmax_steps = 1\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    loaded = campaign_module.load_campaign(tmp_path / "camp" / "tiny.toml")
    assert loaded.scenarios[0].settings.map == str(tmp_path / "camp" / "../maps/flat.npy")
    assert main(["campaign", str(tmp_path / "camp" / "broken.toml"), "--workers", "1"]) == 2
    assert "map 'bad'" in capsys.readouterr().err
    assert not (tmp_path / "camp" / "broken-results").exists()


def test_fresh_forgets_nothing_when_the_cluster_cannot_be_reached(tmp_path, capsys,
                                                                   monkeypatch):
    """`--fresh --scheduler ADDRESS` with no scheduler there deleted the finished episodes,
    then failed to connect: the cluster is now reached before anything is forgotten."""
    from tools import executor

    path = write(tmp_path, runs=1)
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    store = tmp_path / "c-results" / "episodes.jsonl"
    before = store.read_text()
    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)
    assert main(["campaign", str(path), "--fresh", "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err
    assert store.read_text() == before


def test_a_campaign_figure_shows_each_outcome_it_has_and_marks_errors(tmp_path, monkeypatch):
    """A held-out check: a category with no episode came out in the legend in default blue
    ("WRONG (0)" and "error (0)" alike), and an episode that raised left an empty gap."""
    from types import SimpleNamespace

    from matplotlib.figure import Figure

    from tools.campaign_report import write_figures

    def row(seed, outcome, steps):
        return {"seed": seed, "outcome": outcome, "steps": steps, "compute_first_ms": 20.0,
                "compute_after_first_median_ms": 2.0, "compute_after_first_p99_ms": 4.0}

    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: drawn.append(fig))
    write_figures(tmp_path, [(SimpleNamespace(name="map=peaks"),
                              [row(0, "localized", 7), row(1, "error", None)])])
    steps_axes = drawn[0].axes[0]
    labels = [t.get_text() for t in steps_axes.get_legend().get_texts()]
    assert sorted(labels) == ["error (1)", "localized (1)"]
    error_marks = [line for line in steps_axes.get_lines() if line.get_label() == "error (1)"]
    assert list(error_marks[0].get_xdata()) == [1]


def test_a_campaign_folder_moved_elsewhere_resumes(tmp_path, capsys):
    """A held-out check moved a campaign folder (its map file beside it): the scenarios
    were keyed by the map's absolute path, and the run began again ("0 already done")."""
    import shutil

    import numpy as np

    first = tmp_path / "first"
    (first / "maps").mkdir(parents=True)
    np.save(first / "maps" / "flat.npy", np.random.default_rng(0).normal(size=(60, 60)) * 1e-3)
    (first / "c.toml").write_text('runs = 2\n[fixed]\nmap = "maps/flat.npy"\nspacing = 0.005\n'
                                  "max_steps = 2\n")
    assert main(["campaign", str(first / "c.toml"), "--workers", "1"]) == 0
    moved = shutil.move(str(first), str(tmp_path / "moved"))
    capsys.readouterr()
    assert main(["campaign", str(Path(moved) / "c.toml"), "--workers", "1"]) == 0
    assert "2 already done, 0 to run" in capsys.readouterr().out


def test_a_finished_campaign_run_again_shows_no_progress_bar(tmp_path, capsys):
    """A new user re-ran a finished campaign: "18/18 episodes, 00:00 elapsed, ? left", twice."""
    path = write(tmp_path, runs=1)
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    capsys.readouterr()
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    printed = capsys.readouterr()
    assert "2 already done, 0 to run" in printed.out and "2 of 2 episodes finished" in printed.out
    assert "elapsed" not in printed.err


def _map_campaign(tmp_path, grid: str, runs: int = 1) -> Path:
    import numpy as np

    from service.localization.maps import load_map

    np.save(tmp_path / "bumps.npy", load_map("bumps:20:1").heights)
    path = tmp_path / "m.toml"
    path.write_text(f"runs = {runs}\n[fixed]\nspacing = 0.001\nnoise = true\nmax_steps = 3\n"
                    f"[grid]\n{grid}\n")
    return path


def test_one_map_file_by_two_names_is_refused(tmp_path, capsys):
    """A held-out check listed `boss.npy` and `./boss.npy`: the same episodes ran twice and
    counted twice, and a resume ran some of them a third time."""
    path = _map_campaign(tmp_path, 'map = ["bumps.npy", "./bumps.npy"]')
    assert main(["campaign", str(path), "--workers", "1"]) == 2
    assert "are the same settings" in capsys.readouterr().err
    assert not (tmp_path / "m-results").exists()
    os.link(tmp_path / "bumps.npy", tmp_path / "hard.npy")  # a hard link, as a later check
    path.write_text(path.read_text().replace('"./bumps.npy"', '"hard.npy"'))
    assert main(["campaign", str(path), "--workers", "1"]) == 2
    assert "are the same settings" in capsys.readouterr().err


def test_a_localizer_a_map_cannot_take_is_refused_before_any_episode(tmp_path, capsys):
    """A held-out check's grid of algorithms over maps with a profile among them recorded
    every grid episode on the profile as an error, and exited 0."""
    (tmp_path / "row.csv").write_text(",".join(["0.0", "0.001", "0.003", "0.001"] * 30))
    path = tmp_path / "p.toml"
    path.write_text('runs = 1\n[fixed]\nmap = "row.csv"\nspacing = 0.001\nmax_steps = 2\n'
                    '[grid]\nalgorithm = ["particles", "grid"]\n')
    assert main(["campaign", str(path), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "scenario algorithm=grid: the grid localizers need a 2-D map" in err
    assert not (tmp_path / "p-results").exists()


def test_a_changed_map_file_runs_its_episodes_again(tmp_path, capsys):
    """A held-out check replaced a campaign's map file between runs: the resume said "2
    already done, 0 to run" and reported the old map's results as the new one's."""
    import numpy as np

    path = _map_campaign(tmp_path, 'algorithm = ["particles"]\nmap = ["bumps.npy"]', runs=2)
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    np.save(tmp_path / "bumps.npy", np.load(tmp_path / "bumps.npy") * 1.5)
    capsys.readouterr()
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "2 finished episodes ran on another version of their map file" in out
    assert "0 already done, 2 to run" in out
    records = stored(tmp_path / "m-results")
    assert len(records) == 4 and len({r["map_sha256"] for r in records}) == 2
    assert len(episodes(tmp_path / "m-results")) == 2


def test_a_changed_campaign_leaves_no_figures_of_scenarios_it_dropped(tmp_path):
    """A held-out check dropped an algorithm from its grid: the results folder kept the
    dropped scenarios' figures beside the new ones."""
    path = write(tmp_path, runs=1)
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    path.write_text(CAMPAIGN.format(runs=1).replace(', "elimination"', ""))
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    figures = sorted(p.name for p in (tmp_path / "c-results" / "figures").iterdir())
    assert figures == ["00-algorithm_particles_map_bumps_20_1.png"], figures


def test_results_that_cannot_be_written_are_one_line_errors(tmp_path, capsys):
    """A held-out check's `out` inside a file, or under /proc, ended in a traceback."""
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile" / "r", Path("/proc/haptic-results")):
        assert main(["campaign", str(write(tmp_path, runs=1)), "--workers", "1",
                     "--out", str(out)]) == 2
        assert f"cannot write results to {out}" in capsys.readouterr().err


def test_an_episode_that_raised_runs_again_and_the_campaign_says_so(tmp_path, capsys,
                                                                     monkeypatch):
    """A held-out check: episodes that raised counted as done (a rerun never retried them)
    and the campaign exited 0."""
    from tools import executor

    ran = executor.run_one

    def flaky(settings, maps, task=executor.on_map):
        if settings.seed == 1:
            return executor.Failed(settings, "RuntimeError: a worker's bad day")
        return ran(settings, maps, task)

    monkeypatch.setattr(executor, "run_one", flaky)
    path = write(tmp_path, runs=2)
    assert main(["campaign", str(path), "--workers", "1"]) == 1
    assert "2 episodes raised, e.g. scenario" in capsys.readouterr().err
    monkeypatch.setattr(executor, "run_one", ran)
    assert main(["campaign", str(path), "--workers", "1"]) == 0
    assert "2 already done, 2 to run" in capsys.readouterr().out
    assert all(r["outcome"] != "error" for r in episodes(tmp_path / "c-results"))
