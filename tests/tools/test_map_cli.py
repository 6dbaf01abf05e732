"""`haptic map list|check`, and map checks as `haptic run` meets them."""

import json

import numpy as np
import pytest

from service.localization.maps import load_map
from service.localization.presets import names
from tools.cli import main


def test_map_list_names_every_preset(capsys):
    assert main(["map", "list"]) == 0
    out = capsys.readouterr().out
    for name in names():
        assert name in out


def test_map_check_prints_the_report_and_writes_json_and_figure(capsys, tmp_path):
    path = tmp_path / "plate.npy"
    np.save(path, load_map("plate:20:5").heights)
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    assert main(["map", "check", str(path), "--spacing", "0.001", "--json", str(out_json),
                 "--plot", str(out_png)]) == 0
    text = capsys.readouterr().out
    for word in ("heights", "slope", "smallest", "plains", "symmetries"):
        assert word in text
    assert json.loads(out_json.read_text())["plains_share"] > 0
    assert out_png.stat().st_size > 10_000


@pytest.mark.parametrize("radius", ["0.3", "8"])
def test_run_with_a_radius_the_map_cannot_take_is_one_line_and_status_2(capsys, radius):
    assert main(["run", "--quiet", "--radius", radius]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not fit" in err and "Traceback" not in err


def test_map_check_refuses_a_bad_radius_the_same_way(capsys):
    assert main(["map", "check", "peaks", "--radius", "0.3"]) == 2
    assert "does not fit" in capsys.readouterr().err


def test_run_warns_about_a_map_in_millimetres(capsys, tmp_path):
    path = tmp_path / "mm.npy"
    np.save(path, load_map("bumps:20:2").heights * 1000)
    main(["run", "--quiet", "--map", str(path), "--spacing", "0.001", "--max-steps", "2",
          "--algorithm", "elimination", "--policy", "paper"])
    assert "look like millimetres" in capsys.readouterr().out


def test_a_map_check_figure_wraps_its_warnings_to_its_width(tmp_path, monkeypatch):
    """A held-out check: a map check figure's title carried a warning wider than the
    figure, cut off at both edges."""
    from service.localization.map_check import check_map
    from service.localization.maps import load_map
    from tools import map_plots

    shown = []
    monkeypatch.setattr(map_plots.plt, "close", shown.append)
    height_map = load_map("eggcrate")  # it warns of its many symmetries
    report = check_map(height_map, 0.008)
    assert any(len(w) > 120 for w in report.warnings)
    map_plots.check_figure(height_map, report, tmp_path / "check.png")
    (fig,) = shown
    lines = fig._suptitle.get_text().split("\n")
    assert len(lines) > 2 and max(map(len, lines)) <= fig.get_figwidth() * 14


@pytest.mark.parametrize("rows", [1, 121])
def test_a_map_check_figure_says_what_a_step_reads_on_a_tilted_maps_plains(tmp_path,
                                                                         monkeypatch, rows):
    """A held-out check: on a plate scanned off level, the figure said its plains were
    where "a step reads nothing", though a step there reads the slope."""
    from service.localization.map_check import check_map
    from service.localization.surface import HeightMap
    from tools import map_plots

    shown = []
    monkeypatch.setattr(map_plots.plt, "close", shown.append)
    x = np.arange(121) * 0.001
    xx, yy = np.meshgrid(x, x[:rows])
    boss = np.where((np.abs(xx - 0.06) < 0.01) & (np.abs(yy - yy.mean()) <= 0.01), 0.004, 0.0)
    for heights, words in ((boss, "a step reads nothing"),
                           (boss + 0.05 * xx, "a step reads only the slope")):
        height_map = HeightMap(heights, 0.001, "plate")
        map_plots.check_figure(height_map, check_map(height_map, 0.008), tmp_path / "c.png")
        fig = shown.pop()
        texts = [ax.get_title() for ax in fig.axes] + [
            t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]
        assert any(words in t for t in texts), texts


def test_map_check_refuses_a_spacing_the_run_refuses(capsys, tmp_path):
    """The noticed defect: `map check --spacing 1` passed with a warning that the map
    spans metres, and `haptic run` then refused the same spacing."""
    path = tmp_path / "m.npy"
    np.save(path, load_map("bumps:20:2").heights)
    assert main(["map", "check", str(path), "--spacing", "1"]) == 2
    run_said = capsys.readouterr().err
    assert main(["run", "--quiet", "--map", str(path), "--spacing", "1"]) == 2
    assert capsys.readouterr().err.split("error: ")[1] == run_said.split("error: ")[1]
    assert main(["map", "check", str(path), "--spacing", "0.001"]) == 0
