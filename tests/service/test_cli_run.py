"""`haptic run` as a user meets it: output, JSON, determinism, own maps, clear errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from tools.cli import main


def run_cli(*args: str) -> int:
    return main(["run", "--quiet", *args])


def strip_timings(episode: dict) -> dict:
    for step in episode["steps"]:
        step.pop("compute_ms")
        step.pop("policy_ms")
        step.pop("background_ms")
        step.pop("settle_ms")
    return episode


def test_algorithm_iii_run_localizes_and_reports_truth(capsys, tmp_path):
    out = tmp_path / "e.json"
    assert run_cli("--seed", "2", "--algorithm", "elimination", "--policy", "paper",
                   "--json", str(out)) == 0
    text = capsys.readouterr().out
    assert "truth" in text and "estimate" in text and "localized in" in text
    episode = json.loads(out.read_text())
    for key in ("settings", "truth", "steps", "estimate", "converged", "success",
                "true_pose_eliminated"):
        assert key in episode
    assert episode["success"] and episode["true_pose_eliminated"] is False
    step = episode["steps"][0]
    assert {"move", "measurement", "candidates", "compute_ms"} <= set(step)
    assert episode["settings"]["radius"] == 0.008  # SI units


def test_same_seed_same_episode(tmp_path):
    a, b, c = (tmp_path / n for n in ("a.json", "b.json", "c.json"))
    run_cli("--seed", "7", "--noise", "--max-steps", "15", "--json", str(a))
    run_cli("--seed", "7", "--noise", "--max-steps", "15", "--json", str(b))
    run_cli("--seed", "8", "--noise", "--max-steps", "15", "--json", str(c))
    ea, eb, ec = (strip_timings(json.loads(p.read_text())) for p in (a, b, c))
    assert ea == eb
    assert ea != ec


def test_users_own_map_and_start(tmp_path, capsys):
    rng = np.random.default_rng(0)
    from scipy import ndimage

    heights = ndimage.gaussian_filter(rng.normal(0, 1, (121, 161)), 12) * 0.05
    path = tmp_path / "surface.npy"
    np.save(path, heights)
    assert run_cli("--map", str(path), "--spacing", "0.001", "--radius", "0.008",
                   "--start", "0.08,0.06,30", "--algorithm", "elimination",
                   "--sweep", "full", "--headings", "12") == 0
    assert "localized in" in capsys.readouterr().out


def test_profile_map_for_a_planar_finger(tmp_path, capsys):
    x = np.linspace(0, 6 * np.pi, 301)
    profile = (np.sin(x) + 0.5 * np.sin(2.7 * x)) * 0.005
    path = tmp_path / "profile.csv"
    np.savetxt(path, profile[np.newaxis, :], delimiter=",")
    assert run_cli("--map", str(path), "--spacing", "0.001", "--seed", "1",
                   "--algorithm", "elimination") == 0
    assert "truth" in capsys.readouterr().out


@pytest.mark.parametrize("start", ["0.1,0.05,0", "0.1,0,45", "0.1,0,-90"])
def test_a_start_off_a_profile_is_refused_naming_one_on_it(tmp_path, capsys, start):
    """A held-out check: y off the profile was quietly set to 0, and a heading of 45 degrees
    was taken, after which the particles reported poses off the map and elimination
    declared a wrong one."""
    path = tmp_path / "profile.csv"
    np.savetxt(path, (np.sin(np.linspace(0, 12, 201)) * 0.004)[None], delimiter=",")
    assert run_cli("--map", str(path), "--spacing", "0.001", "--start", start) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--start 0.1,0,0 or 0.1,0,180" in err


def test_a_radius_a_profile_cannot_take_names_its_length_and_a_two_row_map_its_rows(
        tmp_path, capsys):
    """"(200 x 0 mm): it must be at most the map's shorter side (200 mm)" on a profile, and
    a two-row CSV meant as a profile was never told that a profile is one row."""
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    np.savetxt(one, np.full((1, 201), 0.01), delimiter=",")
    np.savetxt(two, np.full((2, 201), 0.01), delimiter=",")
    assert run_cli("--map", str(one), "--spacing", "0.001", "--radius", "0.3") == 2
    assert "profile's length" in capsys.readouterr().err
    assert run_cli("--map", str(two), "--spacing", "0.001") == 2
    assert "a single row; this map has 2" in capsys.readouterr().err


def test_plot_is_written(tmp_path):
    png = tmp_path / "fig.png"
    assert run_cli("--seed", "1", "--plot", str(png)) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, message", [
    (["--map", "nope.npy", "--spacing", "0.001"], "does not exist"),
    (["--map", "wavy"], "unknown map preset"),
    (["--radius", "-1"], "--radius"),
    (["--start", "1,2"], "--start"),
    (["--start", "5,5,0"], "outside the map"),
    (["--step", "0.09"], "no room for the starts a noise-free run draws"),
    (["--json", "/no/such/dir/x.json"], "does not exist"),
    (["--sweep", "full", "--algorithm", "elimination", "--max-steps", "0"], "--max-steps"),
    (["--localizer-option", "work"], "NAME=VALUE"),
    (["--localizer-option", "wrok=4000"], "no option 'wrok'; did you mean 'work'? its "
                                          "options: initial, capacity, work"),
])
def test_bad_input_is_one_line_and_status_2(args, message, capsys):
    """One line on standard error, and nothing before it (a start off the map came after
    the map's warning and the run's header)."""
    assert run_cli(*args) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert captured.out == ""


@pytest.mark.parametrize("content, message", [
    (b"\x93NUMPY garbage", "is not a NumPy array of numbers"),
    (None, "3 dimensions"),
    ("nan", "non-finite"),
    ("tiny", "at least 2 samples"),
])
def test_bad_map_files_from_a_real_process(tmp_path, content, message):
    path = tmp_path / "bad.npy"
    if content is None:
        np.save(path, np.zeros((3, 3, 3)))
    elif content == "nan":
        np.save(path, np.array([[0.0, np.nan], [0.0, 0.0]]))
    elif content == "tiny":
        np.save(path, np.zeros((1, 1)))
    else:
        path.write_bytes(content)
    proc = subprocess.run([sys.executable, "-m", "tools.cli", "run", "--map", str(path),
                           "--spacing", "0.001"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_unknown_option_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "--algorithm", "magic"])
    assert exc.value.code == 2


def test_localizer_options_reach_the_localizer(tmp_path):
    out = tmp_path / "e.json"
    assert run_cli("--localizer-option", "initial=500", "--localizer-option", "drop=30.5",
                   "--json", str(out)) == 0
    episode = json.loads(out.read_text())
    assert episode["initial_candidates"] == 500
    assert episode["settings"]["localizer_options"] == {"initial": 500, "drop": 30.5}


def test_a_heading_just_below_zero_prints_as_zero():
    from tools.words import pose_text

    assert "heading    0.0 deg" in pose_text((0.1, 0.1, -1e-9))


def test_each_line_says_this_steps_height_change_and_how_sure(tmp_path, capsys):
    out = tmp_path / "e.json"
    assert main(["run", "--seed", "3", "--json", str(out)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("step ")]
    z = [0.0] + [s["measurement"][2] for s in json.loads(out.read_text())["steps"]]
    printed = [float(ln.split("dz")[1].split("mm")[0]) for ln in lines]
    assert printed == pytest.approx(list(np.diff(z) * 1e3), abs=1e-3)
    assert all("spread" in ln and "leading mode" in ln and "candidates" not in ln
               for ln in lines)


def test_a_run_that_does_not_converge_says_why(capsys):
    assert run_cli("--seed", "3", "--max-steps", "3") == 0
    out = capsys.readouterr().out
    assert "not localized after 3 steps: out of steps (3 of at most 3); still ambiguous " \
           "between x" in out
    assert "from the truth" in out
