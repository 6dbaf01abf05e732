"""B2 `realistic`: continuous start poses, noise and model mismatch (BENCHMARKS.md B2).

200 seeded runs (seeds 0..199) of at most 60 steps with B2's noise always on: continuous
starts at least two step lengths inside the map's edge, a perturbed world the localizer
does not know, noisy steps and readings. Works on any map given with --map.
"""

from __future__ import annotations

import argparse

from service.episode.scenario import RunSettings
from tools.bench_common import B2_DEFAULTS as DEFAULTS
from tools.bench_common import add_bench_options, exit_status, fmt, run_seeded_scenario

TARGETS = {"successes": ">= 198/200", "wrong_declarations": "<= 1", "steps_median": "<= 12",
           "final_position_error_median": "<= 0.5 mm",
           "final_heading_error_deg_median": "<= 1.5 deg"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bench_options(p, defaults=DEFAULTS, runs=200)


def run(args: argparse.Namespace) -> int:
    return exit_status(run_seeded_scenario(args, scenario="realistic", label="B2",
                                           print_table=print_table,
                                           extra={"targets": TARGETS}, noise=True))


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v * 1e3:.3f} mm"


def print_table(s: dict, base: RunSettings) -> None:
    print(f"B2 realistic: {base.algorithm} + {base.policy} on {base.map}, {s['runs']} runs, "
          f"at most {base.max_steps} steps")
    rows = [
        ("successes", f"{s['successes']}/{s['runs']}"),
        ("wrong declarations", str(s["wrong_declarations"])),
        ("steps", f"median {fmt(s['steps_median'], 'g')}, p90 {fmt(s['steps_p90'], 'g')}, "
                  f"max {s['steps_max']}"),
        ("declared pose's error", f"position median {_mm(s['final_position_error_median'])}, "
                                 f"p90 {_mm(s['final_position_error_p90'])}"),
        ("", f"heading median {fmt(s['final_heading_error_deg_median'], '.2f')} deg, "
                                f"p90 {fmt(s['final_heading_error_deg_p90'], '.2f')} deg"),
        ("compute per step", f"first {fmt(s['compute_ms_first_median'])} ms (median), "
                             f"after it median {fmt(s['compute_ms_after_first_median'])} ms, "
                             f"p99 {fmt(s['compute_ms_after_first_p99'])} ms"),
        ("policy per step", f"median {fmt(s['policy_ms_median'])} ms, "
                            f"p99 {fmt(s['policy_ms_p99'])} ms"),
        ("work between steps", f"median {fmt(s['background_ms_median'])} ms, "
                               f"p99 {fmt(s['background_ms_p99'])} ms (while the finger moves)"),
    ]
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
