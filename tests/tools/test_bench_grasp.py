"""`haptic bench grasp` (B6): the summary keys the issue fixes, the ablation and a figure."""

from __future__ import annotations

import json

from tools.bench_grasp import _summary, failed_runs
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


TIMINGS = ("compute_ms_after_first", "policy_ms", "settle_ms")


def test_bench_grasp_runs_where_every_benchmark_runs(tmp_path, capsys):
    """It had a pool of its own: one worker by default, no --scheduler, and no word of how
    many workers shared the machine. A pool of two gives one worker's results."""
    runs = {}
    for workers in ("1", "2"):
        out = tmp_path / f"b6-{workers}.json"
        assert main(["bench", "grasp", "--runs", "2", "--objects", "blob", "--hands",
                     "three-finger", "--max-steps", "6", "--no-ablation", "--no-single",
                     "--workers", workers, "--json", str(out)]) == 0
        assert f"episodes run on {'1 worker' if workers == '1' else 'a local pool of 2'}" \
            in capsys.readouterr().out
        result = json.loads(out.read_text())
        assert result["workers"] == int(workers) and result["cores"] >= 1
        runs[workers] = [{k: v for k, v in o.items() if k not in TIMINGS}
                         for o in result["runs"]["three-finger/blob/gated"]]
    assert runs["1"] == runs["2"] and [o["seed"] for o in runs["1"]] == [0, 1]
    assert main(["bench", "grasp", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"]) == 2
    assert "--workers applies to the local pool" in capsys.readouterr().err


def test_bench_grasp_refuses_an_unknown_family(capsys):
    assert main(["bench", "grasp", "--objects", "cube"]) == 2
    assert "'cube' is neither a family (ellipse, rounded, blob, keyed) nor an object" in \
        capsys.readouterr().err


def test_bench_grasp_refuses_a_hand_it_has_not_and_a_plane_with_no_mesh(capsys):
    """A held-out check: `--hands four-finger` failed in the first episode, as an episode's
    error with exit 1 (a wrong declaration's status), and `--plane` beside outlines only was
    taken without a word, where `haptic run` refuses it."""
    assert main(["bench", "grasp", "--objects", "blob", "--hands", "four-finger",
                 "--runs", "1", "--workers", "1"]) == 2
    assert "--hands: no hand preset or file 'four-finger'" in capsys.readouterr().err
    assert main(["bench", "grasp", "--objects", "blob", "--plane", "z=0.01",
                 "--runs", "1", "--workers", "1"]) == 2
    assert "--plane cuts mesh files" in capsys.readouterr().err


def test_bench_grasp_holds_an_object_of_ones_own_in_every_run(tmp_path, capsys):
    """A researcher's outline was refused: "unknown family"."""
    outline = tmp_path / "part.csv"
    outline.write_text("0,0\n0.05,0\n0.06,0.03\n0.02,0.05\n-0.01,0.03\n0,0\n")
    out = tmp_path / "b6.json"
    assert main(["bench", "grasp", "--runs", "2", "--objects", f"{outline},blob:3", "--hands",
                 "three-finger", "--max-steps", "4", "--no-ablation", "--no-single",
                 "--workers", "1", "--json", str(out)]) == 0
    written = json.loads(out.read_text())
    runs = written["runs"]
    assert [o["object"] for o in runs[f"three-finger/{outline}/gated"]] == [str(outline)] * 2
    # a path has "/" in it: each row of the table says its hand, object and kind
    assert sorted((r["hand"], r["object"], r["kind"]) for r in written["table"].values()) == [
        ("three-finger", str(outline), "gated"), ("three-finger", "blob:3", "gated")]
    assert [(o["object"], o["seed"]) for o in runs["three-finger/blob:3/gated"]] == [
        ("blob:3", 0), ("blob:3", 1)]
    # the least quality's run is named, re-runnable (the column said how low, not where)
    least = min((o for v in runs.values() for o in v), key=lambda o: o["min_quality"])
    named = written["summary"]["quality_min_run"]
    assert named.startswith("--hand three-finger --object ") and f"--seed {least['seed']} " in \
        named and (str(outline) if least["object"] == str(outline) else "blob:3") in named
    assert written["summary"]["quality_min"] == least["min_quality"]
    assert f"least quality {written['summary']['quality_min']:.2f} N: {named}" in \
        capsys.readouterr().out


def test_bench_grasp_lists_each_gated_drop_and_wrong_declaration():
    def run(seed, dropped=False, wrong=False):
        return {"object": f"rounded:{seed}", "seed": seed, "dropped": dropped, "wrong": wrong,
                "steps": 4, "min_quality": 0.1, "position_error": 0.0021,
                "heading_error_deg": 136.0}
    lines = failed_runs({("two-finger", "rounded", "gated"): [run(1), run(7, dropped=True),
                                                               run(8, wrong=True)],
                         ("two-finger", "rounded", "ablation"): [run(7, dropped=True)]}, 60)
    assert lines == ["DROPPED: --hand two-finger --object rounded:7 --seed 7 --noise --max-steps "
                     "60 at step 4 (least quality 0.10 N)",
                     "WRONG: --hand two-finger --object rounded:8 --seed 8 --noise --max-steps 60 "
                     "(2.1 mm, 136.0 deg off)"]


def test_bench_grasp_refuses_a_start_weaker_than_the_threshold(capsys):
    assert main(["bench", "grasp", "--runs", "1", "--start-quality", "0.5"]) == 2
    assert "must be at least the threshold" in capsys.readouterr().err


def test_a_failure_line_names_a_file_by_its_absolute_path(tmp_path, monkeypatch):
    """A held-out check ran with relative paths: the printed line re-ran only from there."""
    (tmp_path / "my hand.toml").write_text("")
    (tmp_path / "part.csv").write_text("")
    monkeypatch.chdir(tmp_path)
    lines = failed_runs({("my hand.toml", "part.csv", "gated"): [
        {"object": "part.csv", "seed": 3, "dropped": False, "wrong": True, "steps": 9,
         "min_quality": 1.0, "position_error": 0.001, "heading_error_deg": 120.0}]}, 60)
    assert lines == [f"WRONG: --hand '{tmp_path / 'my hand.toml'}' --object "
                     f"{tmp_path / 'part.csv'} --seed 3 --noise --max-steps 60 "
                     "(1.0 mm, 120.0 deg off)"]


def test_a_failure_line_reruns_with_the_start_quality_it_had():
    lines = failed_runs({("three-finger", "blob", "gated"): [
        {"object": "blob:4", "seed": 4, "dropped": True, "wrong": False, "steps": 2,
         "min_quality": 0.3}]}, 60, start_n=2.0)
    assert lines == ["DROPPED: --hand three-finger --object blob:4 --seed 4 --noise --max-steps "
                     "60 --start-quality 2 at step 2 (least quality 0.30 N)"]


def test_object_files_in_millimetres_run_and_rerun_with_their_units(tmp_path, capsys):
    """A held-out check: `--objects part_mm.stl` was refused with "give --object-units mm",
    an option the bench did not have (nor --plane, which a mesh's refusal names)."""
    import json
    from pathlib import Path

    import numpy as np

    outline = np.loadtxt(Path(__file__).resolve().parents[1] / "service" / "data"
                         / "rounded_triangle_near_120.csv", delimiter=",")
    part = tmp_path / "part_mm.csv"
    np.savetxt(part, outline * 1000.0, delimiter=",")
    out = tmp_path / "b6.json"
    args = ["bench", "grasp", "--objects", str(part), "--hands", "three-finger", "--runs",
            "1", "--max-steps", "2", "--no-ablation", "--no-single", "--workers", "1"]
    assert main(args) == 2
    assert "give --object-units mm" in capsys.readouterr().err
    assert main([*args, "--object-units", "mm", "--json", str(out)]) == 0
    rerun = json.loads(out.read_text())["summary"]["quality_min_run"]
    assert rerun.endswith("--object-units mm"), rerun
    assert main(["run", *rerun.split()]) in (0, 1)  # the line re-runs the episode


def test_the_median_steps_of_the_runs_that_localized_are_told_apart():
    """A held-out check: two fingers on a helper's pear localized 5 of 30 runs, and the
    table said "steps 0": the median over every run, most stopped at step 0."""

    def outcome(steps: int, success: bool) -> dict:
        return {"steps": steps, "success": success, "wrong": False, "dropped": False,
                "stuck": not success, "manipulations": 0, "min_quality": 1.5,
                "compute_ms_after_first": [], "policy_ms": [], "settle_ms": []}

    summary = _summary([outcome(0, False)] * 3 + [outcome(14, True), outcome(20, True)])
    assert summary["steps_median"] == 0 and summary["steps_median_localized"] == 17
    assert _summary([outcome(0, False)])["steps_median_localized"] is None


def test_bench_grasp_refuses_a_hand_that_cannot_hold_before_any_episode(tmp_path, capsys,
                                                                       monkeypatch):
    """A held-out check: a one-finger hand among the --hands ran the other hands' episodes
    first, then exited 1 (the status of a drop) and wrote no JSON. It is refused up front,
    exit status 2, with `haptic run`'s words; no episode runs."""
    from service.episode import hand_episode

    ran = []
    monkeypatch.setattr(hand_episode, "simulate_hand", lambda *a, **k: ran.append(a))
    out = tmp_path / "b6.json"
    assert main(["bench", "grasp", "--runs", "2", "--objects", "blob,keyed", "--hands",
                 "three-finger,planar", "--no-ablation", "--no-single", "--workers", "1",
                 "--json", str(out)]) == 2
    err = capsys.readouterr().err
    # every pair that cannot hold is named at once (a held-out lab mended one at a time)
    assert "2 of 4 hand-object pairs cannot be held" in err
    assert "--hands planar --objects blob: hand 'planar' has one finger" in err
    assert "--hands planar --objects keyed: hand 'planar' has one finger" in err
    assert "--start-quality" not in err
    assert not ran and not out.exists()
    assert main(["bench", "grasp", "--runs", "1", "--objects", "blob", "--hands",
                 "two-finger", "--no-ablation", "--no-single", "--workers", "1",
                 "--start-quality", "500"]) == 2
    assert "ask less of the start (--start-quality)" in capsys.readouterr().err
    assert not ran


def test_the_figure_names_hands_and_object_files_shortly(tmp_path, monkeypatch):
    """A held-out check: file objects' whole paths ran into one another under the bars,
    and the preset `three-finger` read "three"."""
    import matplotlib.pyplot as plt

    from tools import bench_grasp

    shown = []
    monkeypatch.setattr(plt, "close", shown.append)
    row = {"runs": 2, "successes": 1, "drops": 0, "wrong_declarations": 0, "steps_median": 9}
    hands, families = ["three-finger", "/labs/x/my_hand.toml"], ["blob", "/labs/x/part.stl"]
    table = {f"{h}/{f}/gated": row for h in hands for f in families}
    bench_grasp.grasp_figure(table, hands, families, ["gated"], tmp_path / "b6.png")
    labels = [t.get_text() for t in shown[0].axes[0].get_yticklabels()]
    assert labels == ["three-finger · blob", "three-finger · part", "my_hand · blob",
                      "my_hand · part"]


def test_the_figure_keeps_sixteen_pairs_readable(tmp_path, monkeypatch):
    """A held-out lab's 16 hand-object pairs: their labels, as columns, overlapped till
    none could be read. Rows now, and the figure grows with them: no two labels touch."""
    import matplotlib.pyplot as plt

    from tools import bench_grasp

    shown = []
    monkeypatch.setattr(plt, "close", shown.append)
    row = {"runs": 6, "successes": 3, "drops": 0, "wrong_declarations": 0,
           "steps_median": 0, "stuck": 6}
    hands = ["three-finger", "/lab/three_uneven.toml", "/lab/two_asym.toml", "two-finger"]
    families = ["/lab/rrect_notch.csv", "/lab/almost_sym.csv", "/lab/kidney.csv", "blob"]
    table = {f"{h}/{f}/{k}": row for h in hands for f in families
             for k in ("gated", "single", "ablation")}
    bench_grasp.grasp_figure(table, hands, families, ["gated", "single", "ablation"],
                             tmp_path / "b6.png")
    fig = shown[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in fig.axes[0].get_yticklabels()]
    assert len(boxes) == 16
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    # a pair stuck at its first step has no bar; its 0 is written beside the axis
    assert "0" in [t.get_text().strip() for t in fig.axes[1].texts]


def test_the_table_keeps_its_columns_with_object_files(capsys):
    """A held-out lab's table ran out of its columns where objects were paths."""
    from tools import bench_grasp

    row = {"runs": 6, "successes": 3, "drops": 0, "wrong_declarations": 0, "stuck": 1,
           "steps_median": 9, "steps_median_localized": 8, "quality_min": 1.2,
           "compute_ms_after_first_median": 1.0, "compute_ms_after_first_p99": 2.0}
    hands, families = ["two-finger", "/lab/hands/two_asym.toml"], ["blob", "/lab/kidney.csv"]
    table = {f"{h}/{f}/gated": row for h in hands for f in families}
    summary = {"runs": 24, "successes": 12, "wrong_declarations": 0, "drops": 0,
               "compute_ms_after_first_p99": 2.0, "settles": 0, "settle_ms_p99": None}
    bench_grasp._print(table, summary, hands, families, ["gated"])
    rows = [line for line in capsys.readouterr().out.splitlines() if " ok " in line]
    assert len(rows) == 4 and len({line.index(" ok ") for line in rows}) == 1
    assert "two_asym" in rows[2] and "/lab/" not in rows[2]


def test_units_without_an_object_file_are_refused(capsys):
    """A held-out check: `--object-units mm` with the families alone ran, ignored."""
    assert main(["bench", "grasp", "--runs", "1", "--object-units", "mm"]) == 2
    assert "--object-units applies to object files" in capsys.readouterr().err
