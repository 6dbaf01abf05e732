"""The viewer's model of the stream: what `haptic view` draws."""

import numpy as np

from service.wire.envelope import Message
from tools.viewer import ViewModel


def _msg(topic: str, **body) -> Message:
    return Message(type=topic, seq=0, t_mono_ns=0, t_wall_ns=0, body=body, topic=topic)


def _finger_estimate(episode: int, step: int) -> Message:
    return _msg("estimate", episode=episode, step=step, kind="finger", pose=[0.1, 0.1, 0.0],
                converged=True, displacement=[0.01 * step, 0.0, 0.0], position_sd=1e-4,
                heading_sd=1e-3, mode_mass=1.0)


def _cloud(episode: int, step: int, n: int) -> Message:
    return _msg("cloud", episode=episode, step=step, poses=np.zeros((n, 3)),
                weights=np.full(n, 1.0 / n), total=n)


def test_a_hand_episode_in_a_recording_leaves_the_last_finger_episode_drawn():
    """A recording of a daemon that ran a finger, then a hand: the hand's estimate has no
    displacement (nil, as the protocol says), and `haptic view --from` failed on it with a
    TypeError. The hand's messages are skipped, its cloud too when it came first."""
    view = ViewModel()
    for step in (1, 2):
        view.update(_finger_estimate(1, step))
    view.update(_cloud(1, 2, 5))
    view.update(_cloud(2, 0, 7))  # the hand's cloud, before its first estimate
    view.update(_msg("estimate", episode=2, step=0, kind="hand", pose=None, converged=False,
                     displacement=None))
    view.update(_cloud(2, 1, 7))
    assert view.hand_episodes == {2}
    assert (view.episode, view.step, len(view.cloud), view.converged) == (1, 2, 5, True)
    assert sorted(view.path) == [1, 2]
    view.update(_finger_estimate(3, 1))  # a finger again: drawn anew
    assert (view.episode, view.step, len(view.cloud)) == (3, 1, 0)


class _Stream:
    """A subscriber that hands out the given messages, then silence."""

    def __init__(self, messages):
        self.messages = list(messages)

    def recv(self, timeout_s):
        return self.messages.pop(0) if self.messages else None


def test_a_replays_stream_names_the_map_the_view_draws_on():
    """A held-out lab: `haptic view --png` on `haptic replay --publish` said "no map to
    draw: the daemon did not answer", though the stream's `episode_started` names the map."""
    import argparse

    from tools import view_cli

    args = argparse.Namespace(map=None, source=None)
    view = ViewModel()
    started = _msg("event", event="episode_started", episode=1,
                   settings={"map": "bumps:20:1", "radius": 0.008})
    stream = _Stream([_msg("state", state="active"), started, _finger_estimate(1, 1)])
    height_map = view_cli._map_from_stream(args, stream, view, wait_s=5.0)
    assert height_map is not None and height_map.heights.shape == (201, 201)
    assert view.state == "active"  # what came before the map was drawn too
    hand = _msg("event", event="episode_started", episode=2, settings={"object": "blob"})
    assert view_cli._map_from_stream(args, _Stream([hand]), ViewModel(), wait_s=0.5) is None


def test_a_profile_is_drawn_side_on():
    """A held-out check: `haptic view` on a planar finger's profile drew a map seen from
    above, a line at y = 0 on an axis of micrometres. A profile is drawn as `--plot` draws
    it: heights against x, the path and the hypotheses on it."""
    from matplotlib.figure import Figure

    from service.localization.maps import load_map
    from tools.viewer import draw

    hm = load_map("profile:smooth")
    view = ViewModel()
    for step in (1, 2, 3):
        view.update(_finger_estimate(1, step))
    view.update(_cloud(1, 3, 4))
    ax = Figure().add_subplot(1, 1, 1)
    assert draw(ax, hm, view) is None
    assert ax.get_ylabel() == "height (mm)" and ax.get_xlabel() == "x (mm)"
    low, high = ax.get_ylim()
    assert low < float(hm.heights.min()) * 1e3 and float(hm.heights.max()) * 1e3 < high
    path = next(line for line in ax.get_lines()
                if line.get_label().startswith("path under the estimate"))
    np.testing.assert_allclose(path.get_xdata(), [110.0, 120.0, 130.0])  # 0.1 m + 10 mm steps
