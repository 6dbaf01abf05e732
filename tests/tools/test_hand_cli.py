"""`haptic run --object`: a hand localizes a held object from the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from tools.cli import main


def test_run_a_hand_with_json_and_figure(tmp_path, capsys):
    out, fig = tmp_path / "run.json", tmp_path / "run.png"
    assert main(["run", "--object", "blob:3", "--hand", "three-finger", "--noise", "--seed",
                 "1", "--json", str(out), "--plot", str(fig)]) == 0
    text = capsys.readouterr().out
    assert "localized in" in text and "least quality" in text
    assert "held above the 0.2 N margin" in text
    episode = json.loads(out.read_text())
    assert episode["success"] and not episode["dropped"] and episode["converged"]
    assert episode["hand"] == "three-finger" and episode["object"] == "blob:3"
    assert all(len(s["centres"]) == 3 for s in episode["steps"])
    assert episode["min_quality"] >= episode["settings"]["margin_n"]
    assert fig.stat().st_size > 10_000


def prism(outline: np.ndarray, height: float) -> trimesh.Trimesh:
    """A watertight prism over a star-shaped outline (caps fanned from the centre)."""
    n = len(outline)
    rim = np.vstack([np.column_stack([outline, np.zeros(n)]),
                     np.column_stack([outline, np.full(n, height)]),
                     [[0, 0, 0], [0, 0, height]]])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i], [2 * n, j, i], [2 * n + 1, n + i, n + j]]
    return trimesh.Trimesh(rim, np.array(faces))


def test_a_mesh_cross_section_is_an_object(tmp_path, capsys):
    angles = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    radius = 0.022 + 0.003 * np.exp(-0.5 * (np.angle(np.exp(1j * (angles - 1.0))) / 0.25) ** 2)
    outline = np.column_stack([1.2 * radius * np.cos(angles), radius * np.sin(angles)])
    mesh = prism(outline, 0.02)
    assert mesh.is_watertight
    path = tmp_path / "part.stl"
    mesh.export(path)
    assert main(["run", "--object", str(path), "--plane", "z=0.01", "--hand", "three-finger",
                 "--seed", "2", "--max-steps", "3", "--quiet"]) == 0
    assert "object part" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [
    (["--object", "cube"], "unknown object 'cube'"),
    (["--object", "blob", "--algorithm", "grid"], "unknown algorithm 'grid'"),
    (["--object", "blob", "--hand", "nope"], "no hand preset or file 'nope'"),
    (["--object", "blob", "--margin", "2", "--threshold", "1"],
     "must be at least the disturbance margin"),
    (["--object", "blob", "--start-quality", "0.5"],
     "start grasp quality (0.5 N) must be at least the threshold (1.0 N)"),
    (["--object", "blob", "--plane", "z=0"], "`scenario.plane`) applies to mesh files"),
    # a finger's options were ignored without a word beside --object, --hand beside none
    (["--object", "blob", "--map", "bumps"], "--map applies to a finger on a map"),
    (["--object", "blob", "--radius", "0.02", "--policy", "random"],
     "--radius, --policy apply to a finger on a map"),
    (["--object", "blob", "--step", "0.005"], "a hand's roll per step is --roll"),
    (["--hand", "three-finger"], "--hand three-finger without --object"),
])
def test_user_errors_are_one_line(argv, message, capsys):
    assert main(["run", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_hand_with_no_safe_move_says_why_and_draws_it(tmp_path, capsys):
    """Two fingers on rounded:39 (seed 39), known to start only at the threshold (the
    default, given here too), find every move too risky from the start: the run ends
    undecided, says why in words, and still draws its figure, of an episode of no steps."""
    fig = tmp_path / "stuck.png"
    main(["run", "--object", "rounded:39", "--hand", "two-finger", "--noise", "--seed", "39",
          "--start-quality", "1", "--plot", str(fig)])
    text = capsys.readouterr().out
    assert "not localized after 0 steps: no safe move left (under a pose the readings" in text
    assert fig.stat().st_size > 10_000


def test_a_hand_run_out_of_steps_says_why(capsys):
    """A hand run that ended without a pose said only "not localized"; a finger's names the
    reason. The ellipse, symmetric under a half turn, is still ambiguous after two steps."""
    assert main(["run", "--object", "ellipse", "--hand", "two-finger", "--max-steps", "2",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "not localized after 2 steps: out of steps (2 of at most 2)" in out
    assert "still ambiguous between" in out or "not yet clear of the rest" in out
    # the spread beside the leader's share, as a finger's (a held-out lab read "sd 0.21 mm
    # / 0.84 deg" of a leader at 5 %, 154 degrees off)
    (estimate,) = [line for line in out.splitlines() if line.startswith("estimate")]
    assert "spread" in estimate and "leading mode" in estimate


def test_a_clamped_object_shows_no_grasp_quality(tmp_path, capsys):
    """One finger on a clamped object holds no grasp: its steps printed the quality of a
    one-finger grasp (-0.31 N on blob:12), which means nothing there."""
    out = tmp_path / "run.json"
    assert main(["run", "--object", "blob:12", "--hand", "two-finger", "--single-finger",
                 "--noise", "--seed", "12", "--max-steps", "3", "--json", str(out)]) == 0
    steps = [line for line in capsys.readouterr().out.splitlines() if line.startswith("step")]
    assert steps and not any("quality" in line for line in steps)
    assert all(s["quality"] is None for s in json.loads(out.read_text())["steps"])


def test_no_hold_says_which_finger_or_setting_stands_in_the_way(tmp_path, capsys):
    """Every cause said "too big, too small or too slippery for this hand"."""
    from firmware_if.hand import PRESET_DIR

    text = (PRESET_DIR / "three-finger.toml").read_text()
    far = tmp_path / "far.toml"  # the top finger's base 300 mm up: it reaches nothing
    far.write_text(text.replace("base = [0.000000, 0.085000,", "base = [0.0, 0.3,"))
    assert main(["run", "--hand", str(far), "--object", "blob", "--quiet"]) == 2
    assert "finger 'top' reaches no part of it held at the grasp centre (0.0, 0.0) mm: " \
           "check the finger's base" in capsys.readouterr().err
    assert main(["run", "--hand", "three-finger", "--object", "blob", "--threshold", "50",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the firmest hold found has a quality of" in err and "below the 50 N" in err


def test_an_outline_file_says_where_its_poses_are_measured_from(tmp_path, capsys):
    """An outline shifted by (0.2, 0.1) m gave the same poses with no word of the shift: a
    researcher could not map them back to their drawing."""
    rows = [(0, 0), (0.05, 0), (0.06, 0.03), (0.02, 0.05), (-0.01, 0.03), (0, 0)]
    origins = []
    for name, (dx, dz) in (("here", (0.0, 0.0)), ("moved", (0.2, 0.1))):
        path = tmp_path / f"{name}.csv"
        path.write_text("".join(f"{x + dx},{z + dz}\n" for x, z in rows))
        out = tmp_path / f"{name}.json"
        assert main(["run", "--hand", "three-finger", "--object", str(path), "--quiet",
                     "--max-steps", "1", "--json", str(out)]) == 0
        assert "poses are of its centroid, at (" in capsys.readouterr().out
        origins.append(json.loads(out.read_text())["object_origin"])
    assert np.allclose(np.subtract(origins[1], origins[0]), (0.2, 0.1))


def test_a_run_that_drops_the_object_exits_with_status_1(capsys):
    """A script running `haptic run` could not tell a drop from a success: both exited 0.
    Two fingers on blob:0 without the gate (the ablation) drop it at step 7 (seed 2)."""
    assert main(["run", "--object", "blob", "--hand", "two-finger", "--seed", "2", "--noise",
                 "--no-gate", "--max-steps", "15", "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "DROPPED the object" in out
    # it said "least quality 0.12 N (below 0.2 N the object drops)", which read as the rule,
    # not as what happened (a helper's held-out check)
    assert "below the 0.2 N margin: the object slipped" in out


def test_a_finger_run_declared_wrong_exits_with_status_1(monkeypatch, capsys):
    """The same for a wrong declaration: the run's pose scored against a truth a step away
    (`simulate.score` judged against it) is WRONG, and the exit says so; scored against its
    own truth the same run exits 0."""
    import dataclasses

    from service.episode import simulate

    argv = ["run", "--seed", "0", "--quiet"]
    assert main(argv) == 0
    assert "localized in" in capsys.readouterr().out
    scored = simulate.score
    monkeypatch.setattr(simulate, "score", lambda estimate, truth, step: scored(
        estimate, dataclasses.replace(truth, x=truth.x + step), step))
    assert main(argv) == 1
    assert "result    WRONG" in capsys.readouterr().out


def test_an_object_too_big_for_the_hand_is_called_too_big(tmp_path, capsys):
    """A held-out check's 113 mm square in three fingers was "too big or too small for this
    hand", which says neither which nor by how much."""
    h = 0.0565
    square = tmp_path / "square_113mm.csv"
    square.write_text("\n".join(f"{x},{z}" for x, z in
                                [(-h, -h), (h, -h), (h, h), (-h, h), (-h, -h)]) + "\n")
    assert main(["run", "--hand", "three-finger", "--object", str(square)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "too big for this hand" in err and "half" in err, err


def test_the_least_quality_is_told_apart_from_the_margin():
    """A held-out check's drop read "least quality 0.20 N, below the 0.2 N margin" (it was
    0.196 N)."""
    from tools.hand_cli import _beside

    assert _beside(0.196, 0.2) == "0.196"
    assert _beside(0.2004, 0.2) == "0.2004"
    assert _beside(1.56, 0.2) == "1.56" and _beside(0.12, 0.2) == "0.12"


@pytest.mark.parametrize("obj, said", [
    ("ellipse", "the outline nearly repeats under a turn of 180 degrees"),
    ("tests/service/data/slender_with_unequal_ends.csv", "nearly repeats under a turn of -178"),
    ("blob", None),
])
def test_an_outline_that_nearly_repeats_under_a_turn_is_warned_of(obj, said, capsys):
    """A held-out lab's slender outline (its ends 15 % apart in thickness) got no word of
    its half turn, as a map gets of its symmetries, and one run declared the image."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    path = str(root / obj) if obj.endswith(".csv") else obj
    assert main(["run", "--hand", "three-finger", "--object", path, "--max-steps", "1",
                 "--quiet"]) == 0
    warnings = [line for line in capsys.readouterr().out.splitlines()
                if line.startswith("warning:")]
    assert (said is None and not warnings) or (said is not None and said in warnings[0])


def test_a_hand_not_yet_says_what_holds_the_declaration_back(capsys):
    """A held-out lab read "its fit to every reading, its spread, or another pose ... holds
    it back": three causes, and not which. The judge now says which, as a finger's does."""
    assert main(["run", "--hand", "three-finger", "--object", "blob:37", "--seed", "7",
                 "--max-steps", "6", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "is not yet confirmed: 3 readings since the last turn, of the 4 needed" in out, out
