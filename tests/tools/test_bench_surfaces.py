"""`haptic bench objects|profile`: rows per surface, crashes kept, wrong declarations loud."""

import dataclasses
import json

import pytest

from service.episode.scenario import Score
from tools import executor
from tools.cli import main

SHORT = ["--runs", "2", "--map-seeds", "0", "--max-steps", "4", "--workers", "1"]


def test_objects_reports_every_surface_and_family(tmp_path, capsys):
    out, fig = tmp_path / "o.json", tmp_path / "o.png"
    code = main(["bench", "objects", *SHORT, "--families", "plate,terrain", "--json", str(out),
                 "--plot", str(fig)])
    data = json.loads(out.read_text())
    assert code == (1 if data["total"]["wrong_declarations"] else 0)
    assert [r["surface"] for r in data["surfaces"]] == ["plate:20:0", "terrain:20:0"]
    for row in data["surfaces"]:
        assert row["runs"] == 2
        assert row["successes"] + row["not_yet"] + row["wrong_declarations"] + row["errors"] >= 2
        assert row["compute_ms_after_first_p99"] is not None and row["steps_median"] <= 4
    assert len(data["runs"]) == 4 and fig.stat().st_size > 10_000
    assert "plate (all)" in capsys.readouterr().out


def test_a_raising_episode_is_an_error_and_the_rest_still_run(tmp_path, monkeypatch, capsys):
    real = executor.simulate

    def flaky(settings, height_map):
        if settings.seed == 1:
            raise ValueError("boom\nsecond line")
        return real(settings, height_map)

    monkeypatch.setattr(executor, "simulate", flaky)
    out = tmp_path / "p.json"
    main(["bench", "profile", *SHORT, "--families", "smooth", "--algorithm", "elimination",
          "--policy", "paper", "--json", str(out)])
    row = json.loads(out.read_text())["surfaces"][0]
    assert row["errors"] == 1 and row["error_runs"][0] == {
        "map": "profile:smooth:20:0", "seed": 1, "error": "ValueError: boom"}
    assert row["runs"] == 2 and row["verdict"] == "errors"
    assert "1 episodes raised" in capsys.readouterr().out


def test_wrong_declarations_stand_out_and_fail_the_benchmark(tmp_path, monkeypatch, capsys):
    real = executor.simulate

    def wrong_on_seed_0(settings, height_map):
        report = real(settings, height_map)
        if settings.seed == 0:  # as if it had declared a pose 30 mm / 10 deg away
            report = dataclasses.replace(report, score=Score(0.03, 0.1745, False, True))
        return report

    monkeypatch.setattr(executor, "simulate", wrong_on_seed_0)
    out = tmp_path / "w.json"
    assert main(["bench", "objects", *SHORT, "--families", "shell", "--json", str(out)]) == 1
    text = capsys.readouterr().out
    assert "<-- WRONG" in text and "WRONG DECLARATIONS: 1: shell:20:0 seed 0 (30.0 mm" in text
    row = json.loads(out.read_text())["surfaces"][0]
    assert row["verdict"] == "WRONG" and row["wrong_runs"][0]["seed"] == 0


@pytest.mark.parametrize("args", [["--families", "nosuch"], ["--map-seeds", "a,b"],
                                  ["--map-seeds", "-1"]])
def test_bad_options_are_one_line_errors(args, capsys):
    assert main(["bench", "objects", *args]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("bench", ["objects", "profile", "scale"])
@pytest.mark.parametrize("given", [["--map", "bumps:20:1"], ["--spacing", "0.001"]])
def test_a_map_these_benches_do_not_take_is_refused(bench, given, capsys):
    """A researcher's finding: `bench profile --map profile.csv` listed --map in its help,
    printed that it ignored it and ran 30 preset episodes; --spacing was ignored without a
    word."""
    assert main(["bench", bench, *given, "--runs", "1"]) == 2
    err = capsys.readouterr()
    assert err.out == "" and "--map and --spacing do not apply" in err.err
    assert "bench realistic" in err.err


@pytest.mark.parametrize("bench", ["objects", "profile", "scale"])
def test_these_benches_do_not_offer_a_map_in_their_help(bench, capsys):
    """A held-out check: `bench profile --help` listed --map, which it refuses."""
    with pytest.raises(SystemExit):
        main(["bench", bench, "--help"])
    out = capsys.readouterr().out
    assert "--map-seed" in out or "--sizes" in out
    assert "--map NAME" not in out and "--spacing" not in out


def test_a_map_every_episode_refuses_is_an_input_error(tmp_path, capsys):
    """15 samples at 1 mm leave no start two steps inside the edges: every episode raised
    the same error, and the bench ended with status 1, the status of a wrong declaration."""
    profile = tmp_path / "short.csv"
    profile.write_text(",".join(["0.01"] * 15) + "\n")
    assert main(["bench", "realistic", "--map", str(profile), "--spacing", "0.001",
                 "--runs", "2", "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "every episode refused its settings" in err and "smaller --step" in err
