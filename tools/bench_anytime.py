"""`haptic bench anytime`: how well each localizer keeps to a per-call work budget.

Replays seeded B2 episodes through each localizer, calling `work(Budget.seconds(b))`
until each update completes, and reports the slices per update and the longest slice:
what a real-time tick would have waited at most.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from service.episode.scenario import RunSettings, build_localizer, surface_for
from service.episode.simulate import simulate
from service.localization.localizers.base import Budget, Measurement
from service.registry import LOCALIZERS
from tools.arg_types import integer, number
from tools.bench_common import write_json
from tools.outputs import check_outputs


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--budget-ms", type=number(0.01, 10_000, "ms"), default=2.0,
                   help="time budget per work() call (default: %(default)s ms)")
    p.add_argument("--runs", type=integer(1, 100_000), default=5,
                   help="seeded episodes per algorithm")
    p.add_argument("--algorithms", default=",".join(LOCALIZERS.names()),
                   help="comma-separated (default: all)")
    p.add_argument("--json", type=Path, metavar="FILE", help="write results as JSON")


def measure(algorithm: str, seed: int, budget_s: float) -> tuple[list[float], list[int]]:
    """Slice durations (ms) and slices per update for one replayed B2 episode."""
    settings = RunSettings(seed=seed, algorithm=algorithm, noise=True, max_steps=20)
    steps = simulate(settings).result.steps
    localizer = build_localizer(settings, surface_for(settings), np.random.default_rng(seed))
    localizer.start(Measurement(0, np.zeros(3)))
    durations, per_update = [], []
    for s in steps:
        localizer.begin_update(Measurement(s.index, np.asarray(s.measurement), s.blocked))
        count, done = 0, False
        while not done:
            t0 = time.perf_counter()
            done = localizer.work(Budget.seconds(budget_s))
            durations.append((time.perf_counter() - t0) * 1e3)
            count += 1
        per_update.append(count)
    return durations, per_update


def run(args: argparse.Namespace) -> int:
    check_outputs(args.json)
    rows = []
    print(f"work() under a {args.budget_ms:g} ms budget, {args.runs} B2 episodes each")
    for algorithm in args.algorithms.split(","):
        LOCALIZERS.load(algorithm)
        durations, per_update = [], []
        for seed in range(args.runs):
            d, u = measure(algorithm, seed, args.budget_ms / 1e3)
            durations += d
            per_update += u
        row = {"algorithm": algorithm, "budget_ms": args.budget_ms,
               "slice_ms_median": float(np.median(durations)),
               "slice_ms_p99": float(np.percentile(durations, 99)),
               "slice_ms_max": float(np.max(durations)),
               "slices_per_update_median": float(np.median(per_update))}
        rows.append(row)
        print(f"{algorithm:12s} slice median {row['slice_ms_median']:6.2f}  p99 "
              f"{row['slice_ms_p99']:6.2f}  max {row['slice_ms_max']:6.2f} ms; "
              f"{row['slices_per_update_median']:.0f} slices per update (median)")
    write_json(args.json, {"scenario": "anytime", "rows": rows})
    return 0
