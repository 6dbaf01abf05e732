"""Figures: one episode like the paper's Figure 4, a benchmark like its Figure 5."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from service.episode.simulate import EpisodeReport  # noqa: E402
from service.localization.models import rotate  # noqa: E402
from service.localization.surface import HeightMap  # noqa: E402


def draw_surface(ax: plt.Axes, height_map: HeightMap) -> None:
    """The map as filled contours, in millimetres."""
    x_max, y_max = height_map.extent
    if height_map.is_profile:
        xs = np.linspace(0, x_max, height_map.shape[1]) * 1e3
        ax.plot(xs, height_map.heights[0] * 1e3, color="0.3")
        return
    xs = np.linspace(0, x_max, height_map.shape[1]) * 1e3
    ys = np.linspace(0, y_max, height_map.shape[0]) * 1e3
    ax.contourf(xs, ys, height_map.heights * 1e3, levels=20, cmap="terrain", alpha=0.8)
    ax.set_xlim(0, x_max * 1e3)
    ax.set_ylim(0, y_max * 1e3)
    ax.set_aspect("equal")


def draw_poses(ax: plt.Axes, poses: np.ndarray, where: np.ndarray, length: float,
               color: str = "k", width: float = 0.6) -> None:
    """Each hypothesis as a short line from where it puts the finger along its x axis."""
    if len(poses) == 0:
        return
    hx, hy = np.cos(poses[:, 2]) * length, np.sin(poses[:, 2]) * length
    segments = np.stack([where, where + np.column_stack([hx, hy])], axis=1) * 1e3
    ax.add_collection(LineCollection(segments, colors=color, linewidths=width,
                                    alpha=0.6 if width < 1 else 1.0))


def true_path(report: EpisodeReport) -> np.ndarray:
    """The finger's true centre positions, map frame, from the commanded-and-measured path."""
    steps = report.result.steps
    disp = np.array([[0.0, 0.0]] + [s.measurement[:2] for s in steps])
    t = report.truth
    dx, dy = rotate(np.asarray(t.heading), disp[:, 0], disp[:, 1])
    return np.column_stack([t.x + dx, t.y + dy])


def episode_figure(report: EpisodeReport, path: Path) -> None:
    """Panels after steps 0, 5, 10 and the last: surface, candidates, true path (Figure 4)."""
    height_map = report.height_map
    steps = report.result.steps
    shown = sorted(k for k in report.snapshots if k <= len(steps))
    panels = [(k, report.snapshots[k]) for k in shown]
    last = len(steps)
    if last not in report.snapshots:
        panels.append((last, None))
    path_xy = true_path(report)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.4), squeeze=False)
    for ax, (k, hyp) in zip(axes[0], panels, strict=True):
        draw_surface(ax, height_map)
        disp = np.zeros(2) if k == 0 else np.asarray(steps[k - 1].measurement[:2])
        if hyp is not None:
            dx, dy = rotate(hyp.poses[:, 2], disp[0], disp[1])
            where = np.column_stack([hyp.poses[:, 0] + dx, hyp.poses[:, 1] + dy])
            draw_poses(ax, hyp.poses, where, report.settings.step * 0.8)
            count = len(hyp.poses)
        else:
            count = report.result.estimate.candidates if report.result.estimate else 0
            est = report.result.estimate
            if est is not None and est.pose is not None:
                pose = np.array([est.pose])
                dx, dy = rotate(pose[:, 2], disp[0], disp[1])
                draw_poses(ax, pose, np.column_stack([pose[:, 0] + dx, pose[:, 1] + dy]),
                           report.settings.step * 1.5, color="b", width=2.5)
        ax.plot(path_xy[: k + 1, 0] * 1e3, path_xy[: k + 1, 1] * 1e3, "r-", lw=1.5)
        ax.plot(path_xy[k, 0] * 1e3, path_xy[k, 1] * 1e3, "ro", ms=7, mfc="none", mew=2)
        ax.set_title(f"t = {k}: {count} candidate{'s' if count != 1 else ''}")
        ax.set_xlabel("x (mm)")
    axes[0][0].set_ylabel("y (mm)")
    fig.suptitle(f"{report.settings.algorithm} + {report.settings.policy} on "
                 f"{report.settings.map}: true path in red, candidates as lines along their "
                 f"heading")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def bench_figure(reports: Sequence[EpisodeReport], path: Path, title: str) -> None:
    """Steps histogram, drop-off curves, compute per step, compute vs candidates (Figure 5)."""
    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    steps = [len(r.result.steps) for r in reports]
    ax[0, 0].hist(steps, bins=range(0, max(steps) + 2), color="tab:blue")
    ax[0, 0].set(title="(a) steps to localize", xlabel="steps", ylabel="runs")
    for r in reports:
        counts = [r.result.initial_candidates] + [s.candidates for s in r.result.steps]
        ax[0, 1].plot(range(len(counts)), np.maximum(counts, 1), lw=0.6, alpha=0.5)
    ax[0, 1].set(title="(b) drop-off: candidates left", xlabel="step", ylabel="candidates",
                 yscale="log")
    for r in reports:
        ms = [s.compute_ms for s in r.result.steps]
        ax[1, 0].plot(range(1, len(ms) + 1), ms, ".", ms=2, alpha=0.5, color="tab:green")
    ax[1, 0].set(title="(c) localizer compute per step", xlabel="step", ylabel="ms")
    before = [n for r in reports for n in
              [r.result.initial_candidates] + [s.candidates for s in r.result.steps[:-1]]]
    ms = [s.compute_ms for r in reports for s in r.result.steps]
    ax[1, 1].plot(before, ms, ".", ms=2, alpha=0.5, color="tab:purple")
    ax[1, 1].set(title="(d) compute vs candidates entering the step", xlabel="candidates",
                 ylabel="ms", xscale="log")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
