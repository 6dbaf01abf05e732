"""`haptic bench SCENARIO`: the seeded benchmark scenarios of BENCHMARKS.md.

Each scenario module has `add_arguments(parser)` and `run(args) -> int`; it is imported
only when chosen.
"""

from __future__ import annotations

import argparse
import importlib

SCENARIOS: dict[str, tuple[str, str]] = {
    "paper": ("tools.bench_paper", "B1: the paper's table (103 noise-free runs on peaks)"),
    "realistic": ("tools.bench_realistic", "B2: continuous pose, noise, model mismatch"),
    "scale": ("tools.bench_scale", "B3: compute per step as the map grows"),
    "service": ("tools.bench_service", "B4: the real-time loop under load"),
    "bus": ("tools.bench_bus", "bus cycle time on the servo-bus emulator"),
    "anytime": ("tools.bench_anytime", "longest localizer work slice under a time budget"),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark scenario",
                       description="Seeded benchmark scenarios (see BENCHMARKS.md).")
    scenarios = p.add_subparsers(dest="scenario", metavar="SCENARIO", required=True)
    for name, (module, summary) in SCENARIOS.items():
        sp = scenarios.add_parser(name, help=summary, description=summary)
        mod = importlib.import_module(module)
        mod.add_arguments(sp)
        sp.set_defaults(handler=mod.run)
