"""A live picture of localization, drawn as `haptic run --plot` draws an episode: the map in
millimetres with a height colour bar, the hypotheses where each would put the finger now
(darker = likelier), the estimate and the finger's path under it.

`ViewModel` folds stream messages into what is drawn, so the same code serves the live
window, PNG snapshots and recordings. Episode ids are the daemon's (unique while it runs),
so a new id always starts a new path.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.localization.localizers.base import Hypotheses
from service.localization.surface import HeightMap
from service.wire.envelope import Message
from tools.plots import (
    CLOUD,
    ESTIMATE,
    MM,
    draw_hypotheses,
    draw_surface,
    finger_positions,
    hypothesis_ink,
)
from tools.words import belief_text


@dataclass
class ViewModel:
    """What the picture shows, updated message by message."""

    cloud: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    weights: np.ndarray = field(default_factory=lambda: np.empty(0))
    total: int = 0
    pose: tuple[float, float, float] | None = None
    converged: bool = False
    belief: str = ""
    step: int = 0
    cloud_step: int = -1
    episode: int = 0
    path: dict[int, tuple[float, float]] = field(default_factory=dict)
    """The finger's displacement (finger frame) after each reading seen, by step."""
    state: str = "?"
    hand_episodes: set[int] = field(default_factory=set)
    """Episodes of a hand (an object's pose, no map): not drawn here, their messages
    skipped (a recording may hold both)."""
    _before: ViewModel | None = None
    """The picture before the current episode began, shown again if it turns out a hand's."""

    @property
    def complete(self) -> bool:
        """Converged, with the cloud of the final belief in hand."""
        return self.converged and self.cloud_step == self.step

    def update(self, msg: Message) -> None:
        if msg.topic in ("cloud", "estimate") and msg["episode"] in self.hand_episodes:
            return
        if msg.topic == "estimate" and msg.get("kind") == "hand":
            self.hand_episodes.add(msg["episode"])
            if msg["episode"] == self.episode and self._before is not None:
                self._restore(self._before)  # its cloud came first: drawn by mistake
            return
        if msg.topic == "cloud":
            if msg["episode"] != self.episode:
                self._new_episode(msg["episode"])
            self.cloud = np.asarray(msg["poses"], dtype=np.float64).reshape(-1, 3)
            self.weights = np.asarray(msg["weights"], dtype=np.float64).reshape(-1)
            self.total = int(msg["total"])
            self.cloud_step = int(msg["step"])
        elif msg.topic == "estimate":
            if msg["episode"] != self.episode:
                self._new_episode(msg["episode"])
            self.pose = None if msg["pose"] is None else tuple(msg["pose"])
            self.converged = bool(msg["converged"])
            self.step = int(msg["step"])
            self.belief = belief_text(msg.get("position_sd"), msg.get("heading_sd"),
                                      msg.get("mode_mass"))
            d = msg["displacement"]
            self.path[self.step] = (float(d[0]), float(d[1]))
        elif msg.topic == "state":
            self.state = str(msg["state"])

    def _new_episode(self, episode: int) -> None:
        self._before = dataclasses.replace(self, _before=None)
        self.episode = episode
        self.path = {}
        self.cloud_step = -1
        self.pose = None
        self.converged = False
        self.cloud, self.weights = np.empty((0, 3)), np.empty(0)

    def _restore(self, other: ViewModel) -> None:
        for f in dataclasses.fields(self):
            if f.name not in ("hand_episodes", "state"):  # the daemon's, not an episode's
                setattr(self, f.name, getattr(other, f.name))

    def path_on_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The finger's positions in the map frame under the current estimate (metres), and
        their step numbers (a viewer that joined late has not seen every step)."""
        if self.pose is None or not self.path:
            return np.empty((0, 2)), np.empty(0, int)
        steps = np.array(sorted(self.path))
        moves = np.array([self.path[k] for k in steps]).T
        return finger_positions(np.array([self.pose] * len(steps)), moves), steps


def draw(ax: Any, hm: HeightMap, view: ViewModel) -> Any:
    """Draw one frame on a matplotlib Axes (cleared first); returns the surface's mappable
    for a colour bar."""
    ax.clear()
    if hm.is_profile:
        _draw_profile(ax, hm, view)
        return None
    filled = draw_surface(ax, hm)
    now = view.path.get(view.cloud_step, (0.0, 0.0))
    if len(view.cloud):
        draw_hypotheses(ax, Hypotheses(view.cloud, view.weights), now, 0.006)
        ax.plot([], [], ".", color=CLOUD,
                label=f"hypotheses: finger now ({len(view.cloud)} of {view.total})")
    path, steps = view.path_on_map()
    path = path * MM
    if len(path):
        ax.plot(path[:, 0], path[:, 1], "o", color=ESTIMATE, ms=3,
                label="path under the estimate (steps seen)")
        for k in np.flatnonzero(np.diff(steps) == 1):  # join consecutive steps only
            ax.plot(path[k:k + 2, 0], path[k:k + 2, 1], "-", color=ESTIMATE, lw=1.2)
        pose = np.asarray(view.pose) * [MM, MM, 1]
        ax.plot(*pose[:2], "s", color=ESTIMATE, mfc="none", ms=7, label="estimated start")
        ax.plot(*path[-1], "x", color=ESTIMATE, ms=10, mew=2.5,
                label="finger now (estimate)")
    ax.set_ylabel("y (mm)")
    _title_and_legend(ax, hm, view)
    return filled


def _title_and_legend(ax: Any, hm: HeightMap, view: ViewModel) -> None:
    status = "CONVERGED" if view.converged else view.belief or "waiting for an estimate"
    ax.set_title(f"{hm.name}: episode {view.episode}, step {view.step}: {status} "
                 f"[{view.state}]", fontsize=10)
    if len(view.cloud) or view.pose is not None:
        ax.legend(loc="best", fontsize=7, framealpha=0.85)  # off the path and the cloud


def _draw_profile(ax: Any, hm: HeightMap, view: ViewModel) -> None:
    """A profile side on, heights against x, with each hypothesis, the path and the
    estimate where they put the finger along it (a held-out check: drawn as a map seen
    from above, a profile was a line at y = 0 on an axis of micrometres)."""
    xs = np.linspace(0.0, hm.extent[0], hm.shape[1]) * MM
    heights = hm.heights[0] * MM
    ax.fill_between(xs, heights, heights.min() - 1.0, color="0.85")
    ax.plot(xs, heights, color="0.3", lw=1, label="profile (surface)")

    def on_profile(x: np.ndarray) -> np.ndarray:
        return np.column_stack([x, np.interp(x, xs, heights)])

    now = view.path.get(view.cloud_step, (0.0, 0.0))
    if len(view.cloud):
        order, w, colours = hypothesis_ink(np.asarray(view.weights))
        where = on_profile(finger_positions(np.asarray(view.cloud)[order], now)[:, 0] * MM)
        ax.scatter(where[:, 0], where[:, 1], s=3 + 30 * w, c=colours, linewidths=0)
        ax.plot([], [], ".", color=CLOUD,
                label=f"hypotheses: finger now ({len(view.cloud)} of {view.total})")
    path, _ = view.path_on_map()
    if len(path):
        path = on_profile(path[:, 0] * MM)
        ax.plot(path[:, 0], path[:, 1], "o-", color=ESTIMATE, ms=3, lw=1.2,
                label="path under the estimate (steps seen)")
        start = on_profile(np.array([view.pose[0] * MM]))[0]
        ax.plot(*start, "s", color=ESTIMATE, mfc="none", ms=7, label="estimated start")
        ax.plot(*path[-1], "x", color=ESTIMATE, ms=10, mew=2.5,
                label="finger now (estimate)")
    ax.set(xlim=(0.0, xs[-1]), xlabel="x (mm)", ylabel="height (mm)")
    _title_and_legend(ax, hm, view)


def save_png(path: str, hm: HeightMap, view: ViewModel) -> None:
    """A snapshot without a display."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.6, 6.5), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    filled = draw(ax, hm, view)
    if filled is not None:
        fig.colorbar(filled, ax=ax, label="height (mm)")
    fig.tight_layout()
    fig.savefig(path)
