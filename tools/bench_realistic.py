"""B2 `realistic`: continuous start poses, noise and model mismatch (BENCHMARKS.md B2).

200 seeded runs (seeds 0..199) of at most 60 steps with B2's noise always on: continuous
starts at least two step lengths inside the map's edge, a perturbed world the localizer
does not know, noisy steps and readings. Works on any map given with --map.
"""

from __future__ import annotations

import argparse
import dataclasses

from service.cli_options import settings_from_args
from service.maps import load_map
from service.scenario import RunSettings
from tools.bench_common import (
    add_bench_options,
    check_bench_args,
    fmt,
    run_episodes,
    summarize,
    write_json,
)

RECOMMENDED = {"algorithm": "particles", "policy": "info-gain"}
"""What B2/B3 run unless told otherwise (see the issue-4 report on RunSettings' defaults)."""
DEFAULTS = dataclasses.replace(RunSettings(), noise=True, max_steps=60, **RECOMMENDED)
TARGETS = {"successes": ">= 198/200", "wrong_declarations": "<= 1", "steps_median": "<= 12",
           "final_position_error_median": "<= 0.5 mm",
           "final_heading_error_deg_median": "<= 1.5 deg"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bench_options(p, defaults=DEFAULTS, runs=200)


def run(args: argparse.Namespace) -> int:
    check_bench_args(args)
    base = settings_from_args(args, noise=True)
    height_map = load_map(base.map, base.spacing)
    settings = [settings_from_args(args, noise=True, seed=args.first_seed + i)
                for i in range(args.runs)]
    reports = run_episodes(settings, height_map, desc=f"B2 {base.algorithm}+{base.policy}")
    summary = summarize(reports)
    print_table(summary, base)
    write_json(args.json, {"scenario": "realistic", "settings": base.to_json(),
                           "summary": summary, "targets": TARGETS,
                           "runs": [r.to_json() for r in reports]})
    if args.plot:
        from tools.plots import bench_figure

        bench_figure(reports, args.plot, title=f"B2 {base.algorithm} + {base.policy}")
        print(f"figure written to {args.plot}")
    return 0


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v * 1e3:.3f} mm"


def print_table(s: dict, base: RunSettings) -> None:
    print(f"B2 realistic: {base.algorithm} + {base.policy} on {base.map}, {s['runs']} runs, "
          f"at most {base.max_steps} steps")
    rows = [
        ("successes", f"{s['successes']}/{s['runs']}"),
        ("wrong declarations", str(s["wrong_declarations"])),
        ("steps", f"median {fmt(s['steps_median'], '.0f')}, p90 {fmt(s['steps_p90'], '.0f')}, "
                  f"max {s['steps_max']}"),
        ("final position error", f"median {_mm(s['final_position_error_median'])}, "
                                 f"p90 {_mm(s['final_position_error_p90'])}"),
        ("final heading error", f"median {fmt(s['final_heading_error_deg_median'], '.2f')} deg, "
                                f"p90 {fmt(s['final_heading_error_deg_p90'], '.2f')} deg"),
        ("compute per step", f"first {fmt(s['compute_ms_first_median'])} ms (median), "
                             f"after it median {fmt(s['compute_ms_after_first_median'])} ms, "
                             f"p99 {fmt(s['compute_ms_after_first_p99'])} ms"),
    ]
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
