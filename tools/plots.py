"""Figures a reader understands without the code: one episode (after the paper's Figure 4)
and a benchmark (after its Figure 5), in millimetres and degrees, with colour bars and
legends.

An episode on a 2-D map: the surface, the hypotheses (where each would put the finger
now, shaded by probability), the true path, the truth and the estimate after a few steps
and at the end; below, how the error, the spread and the leading mode's probability
evolved. On a 1-D profile: the profile with the fingertip's path on it, and the
hypotheses as histograms over start position, one colour per direction.

Figures are built on `matplotlib.figure.Figure`, never pyplot, so no GUI backend is ever
involved (and the live viewer can share these helpers).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle
from matplotlib.ticker import MaxNLocator

from service.episode.simulate import EpisodeReport
from service.localization.localizers.base import Hypotheses, wrap_angle
from service.localization.models import rotate
from service.localization.surface import HeightMap
from tools.words import steps_text

MM = 1e3
TRUTH, ESTIMATE, CLOUD = "tab:red", "tab:blue", "0.1"


# -- shared pieces ---------------------------------------------------------------------------
def draw_surface(ax: Axes, height_map: HeightMap) -> Any:
    """The map as filled contours in millimetres; returns the mappable for a colour bar."""
    x_max, y_max = height_map.extent
    xs = np.linspace(0, x_max, height_map.shape[1]) * MM
    ys = np.linspace(0, y_max, height_map.shape[0]) * MM
    filled = ax.contourf(xs, ys, height_map.heights * MM, levels=20, cmap="terrain",
                         alpha=0.85)
    ax.set(xlim=(0, x_max * MM), ylim=(0, y_max * MM), aspect="equal", xlabel="x (mm)")
    return filled


def finger_positions(poses: np.ndarray, displacement: Sequence[float]) -> np.ndarray:
    """Where each start pose (N, 3) puts the finger after `displacement` (finger frame)."""
    dx, dy = rotate(poses[:, 2], displacement[0], displacement[1])
    return np.column_stack([poses[:, 0] + dx, poses[:, 1] + dy])


def hypothesis_ink(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which hypotheses to draw, in drawing order (the likeliest last, on top), their
    weights scaled to the most probable, and their colours: the more probable, the darker;
    thousands of equals a haze, not ink. One rule for maps and profiles, figures and the
    viewer."""
    order = np.argsort(weights)
    w = weights[order] / max(float(weights.max(initial=0.0)), 1e-300)
    keep = w >= 1e-4  # below that a hypothesis holds no belief worth ink
    order, w = order[keep], w[keep]
    crowd = float(np.clip(300 / max(len(w), 1), 0.08, 1.0))
    colours = np.zeros((len(w), 4))
    colours[:, 3] = crowd * (0.05 + 0.95 * w)
    return order, w, colours


def draw_hypotheses(ax: Axes, hyp: Hypotheses, displacement: Sequence[float],
                    tick: float) -> None:
    """Each hypothesis as a dot where it puts the finger now, with a tick along its
    heading (`hypothesis_ink`'s shades)."""
    if len(hyp.poses) == 0:
        return
    order, w, colours = hypothesis_ink(np.asarray(hyp.weights))
    poses = hyp.poses[order]
    where = finger_positions(poses, displacement) * MM
    heads = np.column_stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])]) * tick * MM
    ax.add_collection(LineCollection(np.stack([where, where + heads], axis=1),
                                     colors=colours, linewidths=0.7))
    ax.scatter(where[:, 0], where[:, 1], s=3 + 12 * w, c=colours, linewidths=0)


def true_path(report: EpisodeReport) -> np.ndarray:
    """The finger's true centre positions in the map frame, start first (from the measured
    displacements carried by the true start pose)."""
    disp = np.array([[0.0, 0.0]] + [s.measurement[:2] for s in report.result.steps])
    t = report.truth
    dx, dy = rotate(np.asarray(t.heading), disp[:, 0], disp[:, 1])
    return np.column_stack([t.x + dx, t.y + dy])


def _displacement(report: EpisodeReport, k: int) -> tuple[float, float, float]:
    return (0.0, 0.0, 0.0) if k == 0 else report.result.steps[k - 1].measurement


def _belief_title(report: EpisodeReport, k: int) -> str:
    if k == 0:
        return "before the first move"
    s = report.result.steps[k - 1]
    if s.mode_mass is None or not np.isfinite(s.mode_mass):
        return f"after step {k}"
    return f"after step {k}: the estimate's mode {100 * s.mode_mass:.0f} %"


def _panels(report: EpisodeReport) -> list[tuple[int, Hypotheses | None]]:
    last = len(report.result.steps)
    shown = sorted(k for k in report.snapshots if k < last)
    return [(k, report.snapshots[k]) for k in shown] + [(last, report.snapshots.get(last))]


# -- one episode -----------------------------------------------------------------------------
def episode_figure(report: EpisodeReport, path: Path) -> Figure:
    """The episode as a figure: belief panels above, error/spread/probability below."""
    if report.height_map.is_profile:
        return profile_figure(report, path)
    panels = _panels(report)
    fig = Figure(figsize=(4.0 * len(panels) + 1.2, 8.2))
    grid = fig.add_gridspec(2, len(panels) + 1, height_ratios=(1.35, 1),
                            width_ratios=[1] * len(panels) + [0.06])
    path_xy = true_path(report) * MM
    est = report.result.estimate
    for i, (k, hyp) in enumerate(panels):
        ax = fig.add_subplot(grid[0, i])
        filled = draw_surface(ax, report.height_map)
        disp = _displacement(report, k)
        if hyp is not None:
            draw_hypotheses(ax, hyp, disp, report.settings.step * 0.6)
        ax.plot(path_xy[: k + 1, 0], path_xy[: k + 1, 1], "-", color=TRUTH, lw=1.5)
        ax.plot(*path_xy[0], "s", color=TRUTH, ms=6, mfc="none", mew=1.5)
        ax.plot(*path_xy[k], "o", color=TRUTH, ms=8, mfc="none", mew=2)
        pose = report.result.steps[k - 1].estimate if k else None
        if k == len(report.result.steps) and est is not None:
            pose = est.pose
        if pose is not None:
            here = finger_positions(np.array([pose]), disp)[0] * MM
            ax.plot(*here, "x", color=ESTIMATE, ms=10, mew=2.5)
        done = k == len(report.result.steps)
        ax.set_title(("end, " if done else "") + _belief_title(report, k), fontsize=10)
        if i == 0:
            ax.set_ylabel("y (mm)")
    fig.colorbar(filled, cax=fig.add_subplot(grid[0, -1]), label="height (mm)")
    fig.legend(handles=_legend_handles(), loc="upper center", ncol=5, fontsize=8,
               frameon=False, bbox_to_anchor=(0.5, 0.965))
    summary_axes(fig, grid[1, :-1], report)
    s = report.settings
    fig.suptitle(f"{s.algorithm} + {s.policy} on {s.map}, seed {s.seed}: "
                 f"{_outcome(report)}", y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=110)
    return fig


def _legend_handles() -> list[Line2D]:
    return [
        Line2D([], [], color=TRUTH, lw=1.5, label="true path"),
        Line2D([], [], color=TRUTH, marker="s", ls="", mfc="none", label="true start"),
        Line2D([], [], color=TRUTH, marker="o", ls="", mfc="none", mew=2,
               label="finger now (truth)"),
        Line2D([], [], color=ESTIMATE, marker="x", ls="", mew=2.5,
               label="finger now (estimate)"),
        Line2D([], [], color=CLOUD, marker=".", lw=0.7,
               label="hypotheses: finger now + heading, darker = likelier"),
    ]


def _outcome(report: EpisodeReport) -> str:
    s, steps = report.score, len(report.result.steps)
    if report.result.fault is not None:
        return f"stopped by a hardware fault after {steps_text(steps)}"
    if s.success:
        return f"localized in {steps_text(steps)}"
    if s.wrong_declaration:
        return f"WRONG pose declared after {steps_text(steps)}"
    return f"not localized after {steps_text(steps)}"


def step_errors(report: EpisodeReport) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and heading (rad) error of the estimate after each step (NaN: none)."""
    t = report.truth
    pos, head = [], []
    for s in report.result.steps:
        if s.estimate is None:
            pos.append(np.nan)
            head.append(np.nan)
            continue
        pos.append(np.hypot(s.estimate[0] - t.x, s.estimate[1] - t.y))
        head.append(abs(float(wrap_angle(s.estimate[2] - t.heading))))
    return np.array(pos), np.array(head)


def summary_axes(fig: Figure, cell: Any, report: EpisodeReport) -> None:
    """Error and spread (position, heading) and the leading mode's probability per step."""
    inner = cell.subgridspec(1, 3, wspace=0.3)
    steps = report.result.steps
    n = np.arange(1, len(steps) + 1)
    pos_err, head_err = step_errors(report)
    spread = np.array([[s.position_sd, s.heading_sd, s.mode_mass] for s in steps], float)
    if not len(steps):
        spread = np.empty((0, 3))
    floor_mm, floor_deg = 1e-3, 1e-2  # exact zeros drawn at the floor of the log axis
    ax = fig.add_subplot(inner[0])
    ax.plot(n, np.maximum(pos_err * MM, floor_mm), "-o", ms=3, color=TRUTH,
            label="error of the estimate")
    ax.plot(n, np.maximum(spread[:, 0] * MM, floor_mm), "--", color=ESTIMATE,
            label="spread (sd)")
    ax.set(title="position", xlabel="step", ylabel="mm (0 drawn at 0.001)", yscale="log")
    ax.axhline(0.25 * report.settings.step * MM, color="0.5", lw=0.8, ls=":",
               label="success bound (1/4 step)")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(inner[1])
    ax.plot(n, np.maximum(np.degrees(head_err), floor_deg), "-o", ms=3, color=TRUTH,
            label="error of the estimate")
    ax.plot(n, np.maximum(np.degrees(spread[:, 1]), floor_deg), "--", color=ESTIMATE,
            label="spread (sd)")
    ax.axhline(5.0, color="0.5", lw=0.8, ls=":", label="success bound (5 deg)")
    ax.set(title="heading", xlabel="step", ylabel="degrees (0 drawn at 0.01)", yscale="log")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(inner[2])
    ax.plot(n, spread[:, 2] * 100, "-o", ms=3, color="tab:purple")
    ax.set(title="probability of the leading mode", xlabel="step", ylabel="%",
           ylim=(-3, 103))
    if report.result.converged:
        ax.axvline(len(steps), color="0.3", lw=0.8, ls=":")
        ax.annotate("converged", (len(steps), 50), rotation=90, fontsize=8, ha="right",
                    va="center")


# -- one episode on a profile ----------------------------------------------------------------
PROFILE_INCHES = 9.6
"""About how wide the profile's panel is drawn (inches, of the figure's 12)."""


def profile_figure(report: EpisodeReport, path: Path) -> Figure:
    """A 1-D profile: the profile with the fingertip's path on it; the hypotheses as
    histograms over start position per direction; the summary panels."""
    from service.episode.scenario import surface_for

    hm = report.height_map
    surface = surface_for(report.settings, hm)
    panels = _panels(report)
    path_x = true_path(report)[:, 0]
    z0 = surface.height(report.truth.x, 0.0)
    path_z = z0 + np.array([0.0] + [s.measurement[2] for s in report.result.steps])
    r = report.settings.radius * MM
    low = float(hm.heights[0].min()) * MM - 1
    high = max(float(hm.heights[0].max()) * MM, float(np.max(path_z)) * MM + r) + 2
    # the profile's panel tall enough to show the whole path at equal scales, so that it
    # keeps the width of the panels below it (a range fitted to the profile cut off a
    # path that climbed above it, and its start with it)
    top = max(2.2, PROFILE_INCHES * (high - low) / (hm.extent[0] * MM) * 1.15)
    fig = Figure(figsize=(12, 2.0 + top + 1.6 * len(panels) + 3.4))
    grid = fig.add_gridspec(2 + len(panels), 1,
                            height_ratios=[top] + [1.0] * len(panels) + [2.4])
    ax = fig.add_subplot(grid[0])
    xs = np.linspace(0, hm.extent[0], hm.shape[1])
    ax.fill_between(xs * MM, hm.heights[0] * MM, hm.heights[0].min() * MM - 1, color="0.85")
    ax.plot(xs * MM, hm.heights[0] * MM, color="0.3", lw=1, label="profile (surface)")
    ax.plot(path_x * MM, path_z * MM, "-o", color=TRUTH, ms=3, lw=1.2,
            label="fingertip centre, step by step (truth)")
    ax.plot(path_x[0] * MM, path_z[0] * MM, "s", color=TRUTH, mfc="none", ms=7,
            label="start")
    ax.add_patch(Circle((path_x[-1] * MM, path_z[-1] * MM), r, fill=False,
                            color=TRUTH, lw=1.2, label="fingertip now"))
    est = report.result.estimate
    if est is not None and est.pose is not None:
        ax.axvline(est.pose[0] * MM, color=ESTIMATE, lw=1.2, ls="--",
                   label="estimated start")
    ax.plot([0.0, 0.0], [low, high], alpha=0.0)  # the heights the panel must show
    ax.set(xlim=(0, hm.extent[0] * MM), xlabel="x (mm)", ylabel="height (mm)",
           title=f"{report.settings.map}: {_outcome(report)}")
    # the fingertip drawn round; the heights follow from the panel's size (set above for
    # equal scales), not fixed: matplotlib ignored fixed ones and said so on every profile
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7, loc="best", ncol=2)  # off the path where there is room
    bins = np.linspace(0, hm.extent[0] * MM, 81)
    for i, (k, hyp) in enumerate(panels):
        hax = fig.add_subplot(grid[1 + i], sharex=ax)
        if hyp is not None and len(hyp.poses):
            facing = np.cos(hyp.poses[:, 2]) >= 0
            x0 = hyp.poses[:, 0] * MM
            hax.hist([x0[facing], x0[~facing]], bins=bins, stacked=True,
                     weights=[hyp.weights[facing], hyp.weights[~facing]],
                     color=["tab:green", "tab:orange"],
                     label=["facing +x (heading 0)", "facing -x (heading 180)"])
        hax.axvline(report.truth.x * MM, color=TRUTH, lw=1, label="true start")
        estimate = report.result.steps[k - 1].estimate if k > 0 else None
        if estimate is not None:  # the pool's weights may lean elsewhere: a held-out
            # check read a panel's bars, 95 % at 186 mm, as the 100 % mode at 171 mm
            hax.axvline(estimate[0] * MM, color=ESTIMATE, lw=1.2, ls="--",
                        label="estimated start")
        hax.set_ylabel("probability", fontsize=8)
        hax.set_title("hypotheses over start position (the pool's weights), "
                      + _belief_title(report, k), fontsize=9, loc="left")
        if i == 0:
            hax.legend(fontsize=7, loc="upper right")
    hax.set_xlabel("start position x (mm)")
    summary_axes(fig, grid[-1], report)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return fig


# -- a benchmark -----------------------------------------------------------------------------
def bench_figure(reports: Sequence[EpisodeReport], summary: dict[str, Any], path: Path,
                 title: str, reference_steps: tuple[float, float] | None = None) -> Figure:
    """Steps, outcomes, final errors, the leading mode's probability and compute per step.

    `reference_steps` (mean, sd) marks a published result on the steps histogram."""
    fig = Figure(figsize=(15, 8.4))
    ax = fig.subplots(2, 3)
    steps = np.array([len(r.result.steps) for r in reports])
    a = ax[0, 0]
    a.hist(steps, bins=np.arange(0, steps.max() + 2) - 0.5, color="tab:blue", alpha=0.8)
    a.axvline(steps.mean(), color="tab:blue", lw=2,
              label=f"here: {steps.mean():.1f} ± {steps.std(ddof=min(1, len(steps) - 1)):.1f}")
    # the bench's text gives the median: the figure shows it too
    a.axvline(float(np.median(steps)), color="tab:orange", lw=2, ls=":",
              label=f"median {np.median(steps):g}")
    if reference_steps is not None:
        mean, sd = reference_steps
        a.axvspan(mean - sd, mean + sd, color="0.6", alpha=0.3)
        a.axvline(mean, color="0.3", lw=2, ls="--", label=f"paper: {mean} ± {sd} (shaded)")
    a.set(title="(a) steps per run", xlabel="steps", ylabel="runs")
    for count_axis in (a, ax[0, 2], ax[1, 0]):
        count_axis.yaxis.set_major_locator(MaxNLocator(integer=True))
    a.legend(fontsize=8)
    outcome_bars(ax[0, 1], reports)
    error_histograms(ax[0, 2], ax[1, 0], reports, reports[0].settings.step)
    a = ax[1, 1]
    for r in reports:
        mass = [s.mode_mass * 100 for s in r.result.steps]
        a.plot(range(1, len(mass) + 1), mass, lw=0.6, alpha=0.5)
    a.set(title="(e) probability of the leading mode", xlabel="step", ylabel="%",
          ylim=(-3, 103))
    a = ax[1, 2]
    for r in reports:
        ms = [s.compute_ms for s in r.result.steps]
        a.plot(range(1, len(ms) + 1), ms, ".", ms=2, alpha=0.5, color="tab:green")
    a.set(title="(f) localizer compute per step", xlabel="step", ylabel="ms", yscale="log")
    plain_log_ticks(a.yaxis)
    fig.suptitle(f"{title}: {len(reports)} runs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return fig


def plain_log_ticks(axis: Any) -> None:
    """1, 2, 5, 10, 20 ... on a log axis instead of powers of ten."""
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(ScalarFormatter())
    axis.set_minor_formatter(NullFormatter())


def outcome_bars(ax: Axes, reports: Sequence[EpisodeReport]) -> None:
    """Localized, not yet and wrong declarations as counts."""
    ok = sum(r.score.success for r in reports)
    wrong = sum(r.score.wrong_declaration for r in reports)
    counts = [ok, len(reports) - ok - wrong, wrong]
    bars = ax.bar(["localized", "not yet", "WRONG pose"], counts,
                  color=["tab:green", "0.6", "tab:red"])
    ax.bar_label(bars, labels=[f"{c}/{len(reports)}" for c in counts], fontsize=9)
    ax.set(title="(b) outcome of each run", ylabel="runs", ylim=(0, len(reports) * 1.15))


def error_histograms(pos_ax: Axes, head_ax: Axes, reports: Sequence[EpisodeReport],
                     step: float) -> None:
    """Final position (mm) and heading (deg) errors, success bounds marked, wrong in red."""
    kinds = {"localized": ([], [], "tab:green"), "not yet": ([], [], "0.6"),
             "WRONG pose": ([], [], "tab:red")}
    floors = (1e-4, 1e-3)
    for r in reports:
        s = r.score
        if s.position_error is None:
            continue
        kind = "localized" if s.success else "WRONG pose" if s.wrong_declaration else "not yet"
        kinds[kind][0].append(max(s.position_error * MM, floors[0]))
        kinds[kind][1].append(max(np.degrees(s.heading_error), floors[1]))
    for ax, column, unit, bound, label in (
            (pos_ax, 0, "mm", 0.25 * step * MM, "(c) final position error"),
            (head_ax, 1, "degrees", 5.0, "(d) final heading error")):
        values = [v for _, (*cols, _) in kinds.items() for v in cols[column]]
        if values:
            lo, hi = min(values + [bound]) / 2, max(values + [bound]) * 2
            bins = np.geomspace(lo, hi, 30)
            data = [kinds[k][column] for k in kinds]
            ax.hist(data, bins=bins, stacked=True, color=[kinds[k][2] for k in kinds],
                    label=list(kinds))
        ax.axvline(bound, color="0.3", ls=":", label=f"success bound ({bound:g} {unit})")
        ax.set(title=label, xlabel=f"{unit} (an exact 0 drawn at {floors[column]:g})",
               ylabel="runs", xscale="log")
        ax.legend(fontsize=7)
