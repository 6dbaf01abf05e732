"""B1 `paper`: the paper's table — 103 noise-free runs on peaks, our figures beside its."""

from __future__ import annotations

import argparse

from service.episode.scenario import RunSettings
from tools.bench_common import add_bench_options, fmt, run_seeded_scenario

PAPER = {
    "steps": "23.6 +/- 8.7",
    "first_step_elimination": "~50% mean, 94% best",
    "true_pose_eliminated_runs": "0",
    "compute": "0.7 s/step mean, < 0.04 s/step from step 5 (MATLAB)",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bench_options(p, defaults=RunSettings(), runs=103)


def run(args: argparse.Namespace) -> int:
    if args.noise:
        print("note: B1 is defined noise-free; --noise makes this a different experiment")
    run_seeded_scenario(args, scenario="paper", label="B1", print_table=print_table,
                        extra={"paper": PAPER})
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
        ("policy per step", f"median {fmt(s['policy_ms_median'])} ms, "
                            f"p99 {fmt(s['policy_ms_p99'])} ms", ""),
    ]
    print(f"B1 paper: {base.algorithm} + {base.policy} on {base.map}, {s['runs']} runs")
    width = max(len(r[0]) for r in rows)
    print(f"{'':{width}}  {'haptic-slam':<52}  paper (Algorithm III)")
    for name, ours, theirs in rows:
        print(f"{name:<{width}}  {ours:<52}  {theirs}")
