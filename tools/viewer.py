"""A live picture of localization, after the paper's Figure 4: surface, cloud, estimate, path.

The surface is drawn as filled contours in the map frame; the hypothesis cloud (start-pose
candidates) as dots; the estimated start pose as a star with a heading arrow; the finger's
path as the measured displacements carried onto the map by the estimated pose. `ViewModel`
folds stream messages into what is drawn, so the same code serves live views, PNG
snapshots and recordings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.localization.models import rotate
from service.localization.surface import HeightMap
from service.wire.envelope import Message


@dataclass
class ViewModel:
    """What the picture shows, updated message by message."""

    cloud: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    total: int = 0
    pose: tuple[float, float, float] | None = None
    converged: bool = False
    candidates: int = 0
    episode: int = 0
    path: list[tuple[float, float]] = field(default_factory=list)
    state: str = "?"

    def update(self, msg: Message) -> None:
        if msg.topic == "cloud":
            if msg["episode"] != self.episode:
                self._new_episode(msg["episode"])
            self.cloud = np.asarray(msg["poses"], dtype=np.float64).reshape(-1, 3)
            self.total = int(msg["total"])
        elif msg.topic == "estimate":
            if msg["episode"] != self.episode:
                self._new_episode(msg["episode"])
            self.pose = None if msg["pose"] is None else tuple(msg["pose"])
            self.converged = bool(msg["converged"])
            self.candidates = int(msg["candidates"])
            d = msg["displacement"]
            if not self.path or self.path[-1] != (d[0], d[1]):
                self.path.append((float(d[0]), float(d[1])))
        elif msg.topic == "state":
            self.state = str(msg["state"])

    def _new_episode(self, episode: int) -> None:
        self.episode = episode
        self.path = [(0.0, 0.0)]
        self.pose = None
        self.converged = False

    def path_on_map(self) -> np.ndarray:
        """The finger's path in the map frame under the current estimate."""
        if self.pose is None or not self.path:
            return np.empty((0, 2))
        d = np.asarray(self.path)
        x, y = rotate(np.asarray(self.pose[2]), d[:, 0], d[:, 1])
        return np.column_stack([self.pose[0] + x, self.pose[1] + y])


def draw(ax: Any, hm: HeightMap, view: ViewModel) -> None:
    """Draw one frame on a matplotlib Axes (cleared first)."""
    ax.clear()
    x_max, y_max = hm.extent
    heights = np.atleast_2d(hm.heights)
    if heights.shape[0] > 1:
        ny, nx = heights.shape
        xs, ys = np.linspace(0, x_max, nx), np.linspace(0, y_max, ny)
        ax.contourf(xs, ys, heights * 1e3, levels=20, cmap="terrain", alpha=0.8)
        ax.contour(xs, ys, heights * 1e3, levels=20, colors="k", linewidths=0.3, alpha=0.4)
    if len(view.cloud):
        ax.scatter(view.cloud[:, 0], view.cloud[:, 1], s=6, c="tab:blue", alpha=0.5,
                   label=f"hypotheses ({view.total})")
    path = view.path_on_map()
    if len(path):
        ax.plot(path[:, 0], path[:, 1], "-o", color="tab:red", ms=3, lw=1.5, label="path")
    if view.pose is not None:
        x, y, h = view.pose
        ax.plot([x], [y], "*", color="gold", mec="k", ms=16, label="estimate")
        arrow = 0.05 * max(x_max, y_max)
        ax.arrow(x, y, arrow * np.cos(h), arrow * np.sin(h), width=arrow * 0.05, color="k")
    ax.set_xlim(0, x_max)
    ax.set_ylim(0, max(y_max, 1e-3))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    status = "converged" if view.converged else f"{view.candidates} candidates"
    ax.set_title(f"{hm.name}: episode {view.episode}, {status} [{view.state}]")
    if len(view.cloud) or view.pose is not None:
        ax.legend(loc="upper right", fontsize=8)


def save_png(path: str, hm: HeightMap, view: ViewModel) -> None:
    """A snapshot without a display (Agg), whatever backend pyplot would pick."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6.5), dpi=100)
    FigureCanvasAgg(fig)
    draw(fig.add_subplot(1, 1, 1), hm, view)
    fig.tight_layout()
    fig.savefig(path)
