"""`haptic view`: the daemon's belief as a picture, live in a window or saved as a PNG."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from service.errors import InputError
from service.wire.client import CommandFailed, CommandTimeout
from tools.arg_types import number
from tools.outputs import check_outputs
from tools.signals import interrupted
from tools.stream_cli import add_endpoint_options, client_from, deadline, subscriber_from

MAP_WAIT_S = 10.0
"""How long a live view waits for the stream to name the map when no daemon answers."""


def register(p: argparse.ArgumentParser) -> None:
    p.description = ("Draw the map, the hypotheses (weighted), the estimate and the finger's "
                     "path: live in a window, or (--png) one snapshot without a display; "
                     "--from draws a recording instead of the daemon.")
    p.add_argument("--png", metavar="FILE", help="save one snapshot without a display")
    p.add_argument("--from", dest="source", metavar="RECORDING",
                   help="draw the end of a recording (needs --png)")
    p.add_argument("--duration", type=number(0.01, 86_400, "s"), default=3.0, metavar="S",
                   help="with --png: seconds of stream to collect; stops early on "
                        "convergence (default: %(default)s)")
    p.add_argument("--map", metavar="NAME|PATH",
                   help="map to draw when the daemon cannot be asked (as in haptic run)")
    add_endpoint_options(p, cmd_help="command endpoint, asked for the map")
    p.set_defaults(handler=cmd_view)


def _map_for_view(args: argparse.Namespace, config: dict[str, Any] | None):
    """The height map to draw: --map, else the recording's or the daemon's config."""
    from service.localization.maps import load_map

    if config is None and args.map is None and args.source is None:
        try:
            with client_from(args, timeout_s=2.0, retries=0) as c:
                config = c.call("get_config")
        except (CommandFailed, CommandTimeout):
            config = None
    scenario = (config or {}).get("scenario", {})
    if args.map:
        return load_map(args.map)
    if scenario.get("object"):
        raise InputError(f"{'the recording holds only' if args.source else 'the daemon runs'} "
                         f"a hand holding object '{scenario['object']}': "
                         "`haptic view` draws a finger's belief on its map; follow a hand "
                         "with `haptic watch` or `haptic explore`, or draw one with `haptic "
                         "run --object NAME --plot FILE.png`")
    if "map" not in scenario:
        if args.source is None:
            return None  # the stream may name it (`_map_from_stream`)
        raise InputError("no map to draw: none was recorded; name it with --map")
    return load_map(scenario["map"], scenario.get("spacing"))


def _map_from_stream(args: argparse.Namespace, sub: Any, view: Any, wait_s: float):
    """The map the stream's next `episode_started` names, the messages before it given to
    `view`: a replay (`haptic replay --publish`) has no daemon to ask. None after
    `wait_s` without one."""
    end = deadline(wait_s)
    while time.monotonic() < end and not interrupted():
        msg = sub.recv(min(0.2, max(0.0, end - time.monotonic())))
        if msg is None:
            continue
        settings = msg.get("settings") if msg.topic == "event" else None
        if msg.get("event") == "episode_started" and isinstance(settings, dict) \
                and settings.get("map") and not settings.get("object"):
            return _map_for_view(args, {"scenario": settings})
        view.update(msg)
    return None


def has_display() -> bool:
    """Whether matplotlib would open a window (not Agg or another file-only backend)."""
    import matplotlib
    from matplotlib.backends import BackendFilter, backend_registry

    names = backend_registry.list_builtin(BackendFilter.NON_INTERACTIVE)
    return matplotlib.get_backend().lower() not in {n.lower() for n in names}


def cmd_view(args: argparse.Namespace) -> int:
    from tools.viewer import ViewModel, draw, save_png

    if args.png:  # before any wait: a folder that does not exist was a traceback at the end
        check_outputs(figures=(args.png,))
    view = ViewModel()
    if args.source:
        from tools.recording import read_recording

        if not args.png:
            raise InputError("--from needs --png FILE (a recording has no live view)")
        config, records = read_recording(args.source)
        # the map of the last finger episode (a hand's are skipped), else the config's
        started = [r.message["settings"] for r in records
                   if r.message.get("event") == "episode_started" and r.message.get("settings")
                   and not r.message["settings"].get("object")]
        if started:
            config = {"scenario": started[-1]}
        height_map = _map_for_view(args, config)
        for r in records:
            view.update(r.message)
        if view.hand_episodes:
            print(f"# skipped episode(s) {', '.join(map(str, sorted(view.hand_episodes)))}: "
                  "a hand's; `haptic view` draws a finger's belief on its map", file=sys.stderr)
        save_png(args.png, height_map, view)
        print(f"# wrote {args.png}", file=sys.stderr)
        return 0
    if not args.png and not has_display():
        raise InputError("no display to open a window on; use --png FILE for a snapshot")
    height_map = _map_for_view(args, None)
    with subscriber_from(args, ["state", "estimate", "cloud", "event"]) as sub:
        if height_map is None:  # no daemon answered: a replay's stream names its map
            print("# no daemon answered for the map: waiting for the stream to name it "
                  "(an episode's start), or give --map", file=sys.stderr, flush=True)
            height_map = _map_from_stream(args, sub, view,
                                          args.duration if args.png else MAP_WAIT_S)
            if height_map is None:
                raise InputError("no map to draw: the daemon did not answer and the stream "
                                 "named none (no episode started); name it with --map")
        if args.png:
            end = deadline(args.duration)
            while time.monotonic() < end and not view.complete:
                msg = sub.recv(min(0.2, max(0.0, end - time.monotonic())))
                if msg is not None:
                    view.update(msg)
            save_png(args.png, height_map, view)
            print(f"# wrote {args.png}", file=sys.stderr)
            return 0
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7.6, 6.5))
        plt.ion()
        colour_bar = None
        try:
            while plt.fignum_exists(fig.number) and not interrupted():
                end = time.monotonic() + 0.2
                while (left := end - time.monotonic()) > 0:
                    msg = sub.recv(left)
                    if msg is not None:
                        view.update(msg)
                filled = draw(ax, height_map, view)
                if colour_bar is None and filled is not None:
                    colour_bar = fig.colorbar(filled, ax=ax, label="height (mm)")
                plt.pause(0.01)
        except KeyboardInterrupt:
            pass
    return 0
