"""B1 `paper`: the paper's table — 103 noise-free runs on peaks, our figures beside its."""

from __future__ import annotations

import argparse

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

PAPER = {
    "steps": "23.6 +/- 8.7",
    "first_step_elimination": "~50% mean, 94% best",
    "true_pose_eliminated_runs": "0",
    "compute": "0.7 s/step mean, < 0.04 s/step from step 5 (MATLAB)",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bench_options(p, defaults=RunSettings(), runs=103)


def run(args: argparse.Namespace) -> int:
    check_bench_args(args)
    if args.noise:
        print("note: B1 is defined noise-free; --noise makes this a different experiment")
    base = settings_from_args(args)
    height_map = load_map(base.map, base.spacing)
    settings = [settings_from_args(args, seed=args.first_seed + i) for i in range(args.runs)]
    reports = run_episodes(settings, height_map, desc=f"B1 {base.algorithm}+{base.policy}")
    summary = summarize(reports)
    print_table(summary, base)
    write_json(args.json, {"scenario": "paper", "settings": base.to_json(),
                           "summary": summary, "paper": PAPER,
                           "runs": [r.to_json() for r in reports]})
    if args.plot:
        from tools.plots import bench_figure

        bench_figure(reports, args.plot, title=f"B1 {base.algorithm} + {base.policy}")
        print(f"figure written to {args.plot}")
    return 0


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def print_table(s: dict, base: RunSettings) -> None:
    rows = [
        ("successes", f"{s['successes']}/{s['runs']} (wrong declarations "
                      f"{s['wrong_declarations']})", "103/103 (as reported)"),
        ("steps to a unique pose", f"{s['steps_mean']:.1f} +/- {s['steps_sd']:.1f}, "
                                   f"max {s['steps_max']}", PAPER["steps"]),
        ("first-step elimination", f"{_pct(s['first_step_elimination_mean'])} mean, "
                                   f"{_pct(s['first_step_elimination_max'])} best",
         PAPER["first_step_elimination"]),
        ("true pose eliminated (runs)", fmt(s["true_pose_eliminated_runs"], "d"),
         PAPER["true_pose_eliminated_runs"]),
        ("compute per step", f"first {fmt(s['compute_ms_first_median'])} ms (median), "
                             f"median {fmt(s['compute_ms_median'])} ms, "
                             f"p99 {fmt(s['compute_ms_p99'])} ms", PAPER["compute"]),
    ]
    print(f"B1 paper: {base.algorithm} + {base.policy} on {base.map}, {s['runs']} runs")
    width = max(len(r[0]) for r in rows)
    print(f"{'':{width}}  {'haptic-slam':<52}  paper (Algorithm III)")
    for name, ours, theirs in rows:
        print(f"{name:<{width}}  {ours:<52}  {theirs}")
