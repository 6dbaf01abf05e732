"""`objects`: B2's noise over surfaces like the things a lab puts under a finger.

Several seeded surfaces of each preset family (machined plates, near-symmetric pattern
plates, curved shells, fractal terrain), `--runs` seeded episodes on each, at most 60
steps (BENCHMARKS.md `objects`). Reports per surface and per family: success, "not yet",
wrong declarations, errors, steps (median, p90) and compute (first step, p99 after it).
"""

from __future__ import annotations

import argparse

from service.localization.presets import FAMILIES
from tools.bench_surfaces import add_surface_options, run_families


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_surface_options(p, families=",".join(FAMILIES), seeds="0,1,2", size=20, runs=20)


def run(args: argparse.Namespace) -> int:
    return run_families(args, scenario="objects", label="objects", allowed=FAMILIES,
                        spec="{family}:{size}:{seed}")
