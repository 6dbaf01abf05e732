"""B5 `profile`: the planar finger's job, 1-D profiles under B2's noise (BENCHMARKS.md B5).

Seeded smooth random profiles and profiles cut from the `objects` surfaces (a detailed row
of each, drawn by the seed), at 1 mm. Starts lie at least two steps from the ends, facing
either way (B2's continuous starts on a profile). Reports as `objects`, per profile and
per family.
"""

from __future__ import annotations

import argparse

from service.localization.presets import FAMILIES
from tools.bench_surfaces import add_surface_options, run_families

KINDS = ("smooth", *FAMILIES)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_surface_options(p, families=",".join(KINDS), seeds="0,1,2", size=20, runs=20)


def run(args: argparse.Namespace) -> int:
    return run_families(args, scenario="profile", label="B5 profile", allowed=KINDS,
                        spec="profile:{family}:{size}:{seed}")
