"""`haptic bench SCENARIO`: the seeded benchmark scenarios of BENCHMARKS.md.

Each scenario module has `add_arguments(parser)` and `run(args) -> int`; it is imported
only when chosen. To add a scenario, add a row to SCENARIOS.
"""

from __future__ import annotations

import argparse
import importlib

from tools.cli import Register, add_lazy_commands

SCENARIOS: dict[str, tuple[str, str]] = {
    "paper": ("tools.bench_paper", "B1: the paper's table (103 noise-free runs on peaks)"),
    "realistic": ("tools.bench_realistic", "B2: continuous pose, noise, model mismatch"),
    "scale": ("tools.bench_scale", "B3: compute per step as the map grows"),
    "objects": ("tools.bench_objects", "surfaces like real objects (plates, shells, terrain) "
                                       "under B2's noise (your own map: realistic --map)"),
    "profile": ("tools.bench_profile", "B5: 1-D profiles for the planar finger, B2's noise "
                                       "(your own profile: realistic --map)"),
    "service": ("tools.bench_service", "B4: the real-time loop under load"),
    "soak": ("tools.bench_soak", "the daemon for minutes with subscriber processes "
                                 "reconnecting and stuck: gaps, overruns, memory"),
    "faults": ("tools.bench_faults", "kill the servo bus under hapticd again and again: "
                                     "a latched fault and a reset every time"),
    "bus": ("tools.bench_bus", "bus cycle time on the servo-bus emulator"),
    "hand-bus": ("tools.bench_hand_bus", "a hand on the bus emulator: the read per tick, and "
                                         "seeded episodes beside the simulated ones"),
    "anytime": ("tools.bench_anytime", "longest localizer work slice under a time budget"),
    "grasp": ("tools.bench_grasp", "B6: a hand localizes a held object without dropping it"),
}


def register(p: argparse.ArgumentParser) -> None:
    p.description = "Seeded benchmark scenarios (see BENCHMARKS.md); each prints a table " \
                    "and can write --json and --plot."
    add_lazy_commands(p, SCENARIOS, dest="scenario", metavar="SCENARIO", loader=_scenario)


def _scenario(module: str) -> Register:
    """Registration of one scenario module: its `add_arguments`, with `run` as handler."""

    def register(sp: argparse.ArgumentParser) -> None:
        mod = importlib.import_module(module)
        mod.add_arguments(sp)
        sp.set_defaults(handler=mod.run)

    return register
