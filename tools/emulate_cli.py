"""`haptic emulate`: a Dynamixel servo bus on a pseudo-terminal, with the finger on a surface
or, with `--object`, a hand of several fingers holding an object.

The emulated hand stands at the start pose `haptic run` would draw from the same seed, so
`haptic run --backend dynamixel --port PORT --hand HAND --seed N` on the printed port
localizes the same hidden pose as the simulated finger would; with `--object NAME` (and the
same `--seed`/`--noise`), `haptic run --backend dynamixel --port PORT --hand HAND --object
NAME` explores the object the simulated hand of `haptic run --hand HAND --object NAME` holds.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import TextIO

import numpy as np

from firmware_if.hand import load_hand, presets
from service.episode.scenario import RunSettings, Truth, draw_truth, episode_streams, surface_for
from service.errors import ConfigError
from service.localization.surface import HeightMap
from sim_backend.emulator import ServoBus
from sim_backend.emulator.drills import DrillError, drill
from sim_backend.emulator.hand_plant import HandPlant
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos
from tools.hand_cli import add_object_world_options, hand_settings
from tools.scenario_options import add_scenario_options, settings_from_args
from tools.signals import interrupted

EMULATOR_PRIORITY = 30
"""Above the daemon's loop (`loop.realtime_priority`, 20): starved on a loaded machine, an
ordinary emulator answered late enough to fault an idle bus."""


def register(p: argparse.ArgumentParser) -> None:
    p.description = ("Start a Protocol 2.0 servo-bus emulator whose servos move a fingertip "
                     "over the map, or (with --object) a hand's fingers on the object they "
                     "hold (hardware in the loop); print the port path and serve until "
                     "Ctrl-C.")
    p.add_argument("--hand", required=True, metavar="PRESET|FILE",
                   help=f"hand preset ({', '.join(presets())}) or TOML file")
    add_scenario_options(p, defaults=RunSettings(), localizer=False, radius=False)
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the hidden start pose, as `haptic run` draws it")
    p.add_argument("--start", metavar="X,Y,HEADING_DEG", default=None,
                   help="hidden start pose instead of the seed's (metres, metres, degrees)")
    p.add_argument("--no-fast-read", action="store_true",
                   help="emulate firmware older than v45 (no Fast Sync/Bulk Read)")
    p.add_argument("--priority", type=int, default=EMULATOR_PRIORITY, metavar="N",
                   help="SCHED_FIFO priority (1-98) of the thread that answers, above "
                        "hapticd's loop: servos answer whatever the host does; 0: ordinary "
                        "scheduling (default: %(default)s)")
    p.add_argument("--link", metavar="PATH",
                   help="also make PATH a symlink to the port (a stable name, like "
                        "/dev/serial/by-id/..., that a restarted emulator takes over)")
    g = p.add_argument_group(
        "a hand holding an object (with --object: every finger's servos on one bus, the plant "
        "the simulated hand of `haptic run --hand HAND --object NAME` with the same --seed "
        "and --noise)")
    add_object_world_options(g)
    p.set_defaults(handler=run)


def emulator_truth(settings: RunSettings) -> tuple[Truth, HeightMap]:
    """The start pose `simulate` draws for these settings (same seed, same draw), and the map."""
    surface = surface_for(settings)
    return draw_truth(settings, surface.map, episode_streams(settings.seed)[0]), surface.map


def start_emulator(args: argparse.Namespace) -> tuple[ServoBus, Truth]:
    if getattr(args, "object", None) is not None:
        stray = [flag for flag, given in (("--map", args.map != RunSettings().map),
                                          ("--spacing", args.spacing is not None)) if given]
        if stray:  # a held-out check's `--object blob --map bumps` ignored the map
            raise ConfigError(f"{' and '.join(stray)} belong{'s' if len(stray) == 1 else ''} "
                              "to a finger's map; a hand holding --object has none: leave "
                              f"{'it' if len(stray) == 1 else 'them'} out")
        return start_hand_emulator(args)
    hand = load_hand(args.hand)
    settings = settings_from_args(args, radius=hand.radius)
    truth, height_map = emulator_truth(settings)
    plant = FingerPlant(hand, height_map, truth.as_tuple())
    return _bus(args, hand_bus_servos(hand, plant), plant), truth


def start_hand_emulator(args: argparse.Namespace) -> tuple[ServoBus, Truth]:
    """The hand of `args.hand` holding `args.object` where the seed puts it, on one bus."""
    from service.episode.hand_episode import simulated_hand
    from service.episode.hand_scenario import load_parts

    settings = hand_settings(args)
    parts = load_parts(settings)  # refuses a hand of one finger
    sim, start = simulated_hand(settings, parts)
    plant = HandPlant(sim)
    bus = _bus(args, hand_bus_servos(parts.hand, plant), plant)
    x, z, heading = start
    return bus, Truth(x, z, heading)


def _bus(args: argparse.Namespace, servos, plant) -> ServoBus:
    link = getattr(args, "link", None)
    if link is not None and os.path.exists(link) and not os.path.islink(link):
        raise ConfigError(f"--link {link}: a file that is not a symlink is there already")
    if link is not None and not os.path.isdir(os.path.dirname(os.path.abspath(link))):
        raise ConfigError(f"--link {link}: folder {os.path.dirname(link) or '.'} does not "
                          "exist; make it first or name a link in a folder that does")
    priority = getattr(args, "priority", 0)
    if not 0 <= priority <= 98:
        raise ConfigError(f"--priority {priority}: SCHED_FIFO priorities are 1-98 (0: "
                          "ordinary scheduling)")
    return ServoBus(servos, plant=plant, fast_read=not args.no_fast_read, link=link,
                    priority=priority).start()


def run(args: argparse.Namespace, *, ready: Callable[[str], None] | None = None,
        stop: threading.Event | None = None,
        drills: TextIO | Iterator[str] | None = None) -> int:
    bus, truth = start_emulator(args)
    stop = stop or threading.Event()
    try:
        print(bus.port, flush=True)
        where = (f"holding '{args.object}' at hidden x={truth.x:.4f} m, z={truth.y:.4f} m"
                 if getattr(args, "object", None) is not None else
                 f"at hidden start x={truth.x:.4f} m, y={truth.y:.4f} m")
        print(f"emulating hand '{args.hand}' (ids {sorted(bus.servos)}) {where}, "
              f"heading={np.degrees(truth.heading):.1f} deg; Ctrl-C to stop; fault drills on "
              "standard input ('help' lists them)", flush=True)
        if bus.scheduling is not None and bus.scheduling.note:
            print(f"note: {bus.scheduling.note}", file=sys.stderr, flush=True)
        if drills is None and sys.stdin is not None and sys.stdin.isatty():
            # started with `&` from an interactive shell, a read of the terminal would stop
            # the whole emulator (SIGTTIN) and it would serve nothing; ignored, such a read
            # fails instead, and the drills wait for the foreground (`_typed`)
            signal.signal(signal.SIGTTIN, signal.SIG_IGN)
            drills = _typed(sys.stdin, stop)
        threading.Thread(target=_drills, args=(bus, drills or sys.stdin), daemon=True).start()
        if ready:
            ready(bus.port)
        while not stop.wait(0.5) and not interrupted():
            pass
    except KeyboardInterrupt:
        pass
    finally:
        bus.stop()
        print(f"served {bus.stats['rx_packets']} packets", flush=True)
    return 0


def _typed(terminal: TextIO, stop: threading.Event) -> Iterator[str]:
    """Lines typed at a terminal, read only while the emulator runs in its foreground (after
    `fg`); in the background the emulator serves on without them."""
    fd = terminal.fileno()
    while not stop.is_set():
        try:
            if os.tcgetpgrp(fd) != os.getpgrp():
                stop.wait(0.5)  # in the background: look again after a while
                continue
            line = terminal.readline()
        except OSError:  # moved to the background while reading, or no terminal of ours
            stop.wait(0.5)
            continue
        if not line:
            return
        yield line


def _drills(bus: ServoBus, lines: TextIO | Iterator[str]) -> None:
    """Fault drills typed or piped in (`sim_backend.emulator.drills`), one answer a line,
    until the input ends (a closed or absent standard input ends nothing else)."""
    try:
        for line in lines:
            if line.strip():
                try:
                    print(drill(bus, line), flush=True)
                except DrillError as exc:
                    print(f"drill refused: {exc}", flush=True)
    except (OSError, ValueError):  # no usable standard input: serve on without drills
        return
