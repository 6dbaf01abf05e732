"""B1 `paper`: the paper's table — 103 noise-free runs on peaks, our figures beside its."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from service.episode.scenario import RunSettings, build_localizer, surface_for
from service.episode.simulate import EpisodeReport
from service.localization.localizers.base import Measurement, update
from tools.bench_common import add_bench_options, exit_status, fmt, run_seeded_scenario

PAPER_STEPS = (23.6, 8.7)
"""The paper's steps to a unique pose on B1, mean and sd (Algorithm III in MATLAB)."""
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
    return exit_status(run_seeded_scenario(args, scenario="paper", label="B1",
                                           print_table=print_table, extra={"paper": PAPER},
                                           more_summary=first_step_summary, figure=b1_figure))


def first_move_elimination(report: EpisodeReport) -> float | None:
    """The fraction of the B1 pose table (every step-pitch position x `headings` headings)
    that Algorithm III, as the paper runs it, rules out with the run's first reading: what
    the paper's ~50 % measures, whatever localizer made the run (a bounded pool's own count
    says nothing about it)."""
    if not report.result.steps:
        return None
    settings = dataclasses.replace(report.settings, algorithm="elimination",
                                   localizer_options={"sweep": "paper"})
    table = build_localizer(settings, surface_for(settings, report.height_map),
                            np.random.default_rng(0))
    table.start(Measurement(step=0, displacement=np.zeros(3)))
    before = table.estimate().candidates
    first = report.result.steps[0]
    update(table, Measurement(step=1, displacement=np.asarray(first.measurement),
                              blocked=first.blocked))
    return 1 - table.estimate().candidates / before


def first_step_summary(reports: list[EpisodeReport]) -> dict[str, Any]:
    drops = [d for d in map(first_move_elimination, reports) if d is not None]
    return {"first_step_elimination_mean": float(np.mean(drops)) if drops else None,
            "first_step_elimination_max": float(np.max(drops)) if drops else None}


def on_papers_map(settings: RunSettings) -> bool:
    """Whether a run is on the paper's own map, the only one its results can stand beside
    (a held-out researcher's own map was shown beside the paper's `peaks` figures)."""
    return settings.map == "peaks"


def b1_figure(reports: list[EpisodeReport], summary: dict[str, Any], path, title: str):
    from tools.plots import bench_figure

    papers = bool(reports) and on_papers_map(reports[0].settings)
    return bench_figure(reports, summary, path, title,
                        reference_steps=PAPER_STEPS if papers else None)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def print_table(s: dict, base: RunSettings) -> None:
    rows = [
        ("successes", f"{s['successes']}/{s['runs']} (wrong declarations "
                      f"{s['wrong_declarations']})", "103/103 (as reported)"),
        ("steps to a unique pose", f"{s['steps_mean']:.1f} +/- {s['steps_sd']:.1f}, "
                                   f"max {s['steps_max']}", PAPER["steps"]),
        ("table eliminated by move 1", f"{_pct(s['first_step_elimination_mean'])} mean, "
                                       f"{_pct(s['first_step_elimination_max'])} best "
                                       "(of the pose table)",
         PAPER["first_step_elimination"]),
        ("true pose eliminated (runs)", fmt(s["true_pose_eliminated_runs"], "d"),
         PAPER["true_pose_eliminated_runs"]),
        ("compute per step", f"first {fmt(s['compute_ms_first_median'])} ms (median), "
                             f"median {fmt(s['compute_ms_median'])} ms, "
                             f"p99 {fmt(s['compute_ms_p99'])} ms", PAPER["compute"]),
        ("policy per step", f"median {fmt(s['policy_ms_median'])} ms, "
                            f"p99 {fmt(s['policy_ms_p99'])} ms", ""),
        ("work between steps", f"median {fmt(s['background_ms_median'])} ms, "
                               f"p99 {fmt(s['background_ms_p99'])} ms (while the finger moves)",
         ""),
    ]
    print(f"B1 paper: {base.algorithm} + {base.policy} on {base.map}, {s['runs']} runs")
    width = max(len(r[0]) for r in rows)
    if not on_papers_map(base):  # the paper's figures are of peaks alone
        for name, ours, _ in rows:
            print(f"{name:<{width}}  {ours}")
        return
    print(f"{'':{width}}  {'haptic-slam':<52}  paper (Algorithm III)")
    for name, ours, theirs in rows:
        print(f"{name:<{width}}  {ours:<52}  {theirs}")
