"""What every `haptic bench` scenario shares: options, the seeded run loop, the summary."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from service.bounds import bound_of
from service.episode.scenario import RunSettings
from service.episode.simulate import EpisodeReport
from service.errors import ConfigError, InputError, ServiceError
from service.localization.map_check import check_map
from service.localization.maps import load_map
from service.localization.surface import HeightMap
from tools.executor import (
    Executor,
    Failed,
    InProcess,
    Outcome,
    add_executor_options,
    make_executor,
)
from tools.outputs import check_outputs
from tools.scenario_options import add_scenario_options, settings_from_args


def add_bench_options(parser: argparse.ArgumentParser, *, defaults: RunSettings,
                      runs: int, workers: int | None = None, **scenario: Any) -> None:
    """The scenario options of `haptic run` plus --runs, --first-seed, --json, --plot and
    where the episodes run (--workers, default `workers` or one per core; --scheduler)."""
    add_scenario_options(parser, defaults=defaults, **scenario)
    parser.add_argument("--runs", type=int, default=runs,
                        help="number of seeded runs (default: %(default)s)")
    parser.add_argument("--first-seed", type=int, default=0,
                        help="seed of the first run; runs use consecutive seeds (default: "
                             "%(default)s)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write results as JSON")
    parser.add_argument("--plot", type=Path, metavar="FILE.png", help="write a figure")
    add_executor_options(parser, default_workers=(
        "the number of cores" if workers is None else
        f"{workers}, so compute per step is timed without contention"))
    parser.set_defaults(workers=workers)


def check_bench_args(args: argparse.Namespace) -> None:
    """The bench's own options, before a map is loaded (a held-out check was told of
    `--seed` for `--first-seed -1`, and of `--workers 0` after the map's warnings)."""
    if args.runs < 1:
        raise ConfigError(f"--runs must be at least 1, got {args.runs}")
    check_seeds(getattr(args, "first_seed", 0), args.runs)
    check_outputs(args.json, figures=(args.plot,))


def check_seeds(first: int, count: int, counted: str = "--runs") -> None:
    """`count` consecutive seeds from `first` must all be seeds: a held-out check's
    `--first-seed 9223372036854775807` was told of `--seed` 9223372036854775808."""
    largest = int(bound_of(RunSettings, "seed").hi)
    if first < 0 or first + count - 1 > largest:
        raise ConfigError(f"--first-seed {first} with {counted} {count} gives seeds outside "
                          f"0..{largest}")


LOG_EVERY_S = 30.0
"""Seconds between progress lines when stderr is not a terminal."""


FALLBACK_SIZE = (80, 24)
"""Columns and rows taken for a terminal that tells none."""


def _columns(stream: Any) -> int:
    """The terminal's width in columns (0 when it tells none)."""
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (OSError, ValueError, AttributeError):
        return 0


def progress(total: int, desc: str, unit: str = "run", initial: int = 0) -> tqdm:
    """A progress bar on a terminal; in a log or a pipe, a line at the start, every
    `LOG_EVERY_S` and at the end, so a long run is never silent (a held-out check waited 22
    minutes for the first word of `haptic bench grasp > log`)."""
    if sys.stderr.isatty():
        # a terminal that says it is 0 x 0 (a bare pseudo-terminal) made tqdm cut every
        # line to nothing and hide the bar below its last row: no progress at all
        size = {} if _columns(sys.stderr) else {"ncols": FALLBACK_SIZE[0],
                                                "nrows": FALLBACK_SIZE[1]}
        return tqdm(total=total, desc=desc, unit=unit, initial=initial, leave=False, **size)
    return tqdm(total=total, desc=desc, unit=unit, initial=initial, mininterval=LOG_EVERY_S,
                bar_format="{desc}: {n_fmt}/{total_fmt} " + unit
                + "s, {elapsed} elapsed, {remaining} left{postfix}\n")


def collect(executor: Executor, settings: Sequence[RunSettings],
            maps: dict[str, HeightMap], desc: str) -> list[Outcome]:
    """Every episode's outcome, in the order of `settings`, with one progress bar."""
    outcomes: list[Outcome | None] = [None] * len(settings)
    ok = 0
    with progress(len(settings), desc) as bar:
        for index, outcome in executor.run(settings, maps):
            outcomes[index] = outcome
            ok += isinstance(outcome, EpisodeReport) and outcome.score.success
            bar.set_postfix(ok=ok, refresh=False)
            bar.update()
    return outcomes  # type: ignore[return-value]


def run_episodes(settings: Sequence[RunSettings], height_map: HeightMap | None = None,
                 desc: str = "runs", executor: Executor | None = None) -> list[EpisodeReport]:
    """Run every episode (in this process unless an executor is given); the map is loaded
    once and shared. An episode that raises stops the benchmark, naming it."""
    if height_map is None and settings:
        height_map = load_map(settings[0].map, settings[0].spacing)
    maps = {s.map: height_map for s in settings}
    outcomes = collect(executor or InProcess(), settings, maps, desc)
    failed = [o for o in outcomes if isinstance(o, Failed)]
    if failed and len(failed) == len(outcomes) and all(f.refused for f in failed):
        raise InputError(f"every episode refused its settings, e.g. seed "
                         f"{failed[0].settings.seed} on {failed[0].settings.map}: "
                         f"{failed[0].error}")
    if failed:
        raise ServiceError(f"{len(failed)} of {len(outcomes)} episodes raised, e.g. seed "
                           f"{failed[0].settings.seed} on {failed[0].settings.map}: "
                           f"{failed[0].error}")
    return outcomes  # type: ignore[return-value]


def executor_for(args: argparse.Namespace) -> Executor:
    """The executor --workers / --scheduler ask for; says where the episodes run."""
    executor = make_executor(args.workers, args.scheduler)
    print(f"episodes run on {executor.describe()}")
    return executor


def run_seeded_scenario(args: argparse.Namespace, *, scenario: str, label: str,
                        print_table: Callable[[dict[str, Any], RunSettings], None],
                        extra: dict[str, Any] | None = None,
                        more_summary: Callable[[list[EpisodeReport]], dict[str, Any]]
                        | None = None,
                        figure: Callable[..., None] | None = None,
                        **overrides: Any) -> list[EpisodeReport]:
    """The body of a seeded scenario: consecutive seeds, summary table, JSON, figure.

    `more_summary(reports)` adds the scenario's own figures to the summary; `figure(reports,
    summary, path, title)` draws its plot (default: `plots.bench_figure`)."""
    check_bench_args(args)
    base = settings_from_args(args, **overrides)
    height_map = load_map(base.map, base.spacing)
    for warning in check_map(height_map, base.radius, base.step).warnings:
        print(f"warning: {warning}")
    settings = [settings_from_args(args, seed=args.first_seed + i, **overrides)
                for i in range(args.runs)]
    title = f"{label} {base.algorithm} + {base.policy}"
    with executor_for(args) as executor:
        reports = run_episodes(settings, height_map, desc=title, executor=executor)
    summary = summarize(reports)
    if more_summary is not None:
        summary.update(more_summary(reports))
    print_table(summary, base)
    for line in wrong_declarations(reports):
        print(line)
    write_json(args.json, {"scenario": scenario, "settings": base.to_json(),
                           "summary": summary, **executor.info(), **(extra or {}),
                           "runs": [r.to_json() for r in reports]})
    if args.plot:
        if figure is None:
            from tools.plots import bench_figure as figure
        figure(reports, summary, args.plot, title)
        print(f"figure written to {args.plot}")
    return reports


def wrong_declarations(reports: Sequence[EpisodeReport]) -> list[str]:
    """A line per wrong declaration, with the `haptic run` that repeats it."""
    lines = []
    for r in reports:
        if r.score.wrong_declaration:
            s = r.settings
            spacing = "" if s.spacing is None else f" --spacing {s.spacing:g}"
            lines.append(
                f"WRONG: seed {s.seed}, {r.score.position_error * 1e3:.1f} mm and "
                f"{np.degrees(r.score.heading_error):.1f} deg off: haptic run --map {s.map}"
                f"{spacing} --radius {s.radius:g} --step {s.step:g} --algorithm {s.algorithm} "
                f"--policy {s.policy}{' --noise' if s.noise else ''} --seed {s.seed} "
                f"--max-steps {s.max_steps}")
    return lines


def exit_status(reports: Sequence[EpisodeReport]) -> int:
    """1 when a run declared a wrong pose (a bench's gravest finding), else 0."""
    return int(any(r.score.wrong_declaration for r in reports))


B2_DEFAULTS = dataclasses.replace(RunSettings(), noise=True, max_steps=60)
"""The recommended algorithm and policy (RunSettings' defaults), with B2's noise."""


def percentile(values: Iterable[float], q: float) -> float | None:
    arr = np.asarray(list(values), dtype=float)
    return None if arr.size == 0 else float(np.percentile(arr, q))


def summarize(reports: Sequence[EpisodeReport]) -> dict[str, Any]:
    """The summary every scenario's JSON carries (keys fixed by the issues)."""
    steps = np.array([len(r.result.steps) for r in reports], dtype=float)
    first_ms = [r.result.steps[0].compute_ms for r in reports if r.result.steps]
    all_ms = [s.compute_ms for r in reports for s in r.result.steps]
    later_ms = [s.compute_ms for r in reports for s in r.result.steps[1:]]
    policy_ms = [s.policy_ms for r in reports for s in r.result.steps]
    background_ms = [s.background_ms for r in reports for s in r.result.steps]
    eliminated = [r.true_pose_eliminated for r in reports]
    # the errors of declared poses: a "not yet" run's leading guess is no answer, and its
    # error had counted in the median beside theirs
    ok = [r for r in reports if r.result.converged and r.score.position_error is not None]
    return {
        "runs": len(reports),
        "successes": int(sum(r.score.success for r in reports)),
        "wrong_declarations": int(sum(r.score.wrong_declaration for r in reports)),
        "converged": int(sum(r.result.converged for r in reports)),
        "steps_mean": float(steps.mean()),
        "steps_sd": float(steps.std(ddof=1)) if len(steps) > 1 else 0.0,
        "steps_median": float(np.median(steps)),
        "steps_p90": float(np.percentile(steps, 90)),
        "steps_max": int(steps.max()),
        "true_pose_eliminated_runs": (None if all(e is None for e in eliminated)
                                      else int(sum(bool(e) for e in eliminated))),
        "compute_ms_first_median": percentile(first_ms, 50),
        "compute_ms_median": percentile(all_ms, 50),
        "compute_ms_p99": percentile(all_ms, 99),
        "compute_ms_after_first_median": percentile(later_ms, 50),
        "compute_ms_after_first_p99": percentile(later_ms, 99),
        "policy_ms_median": percentile(policy_ms, 50),
        "policy_ms_p99": percentile(policy_ms, 99),
        "background_ms_median": percentile(background_ms, 50),
        "background_ms_p99": percentile(background_ms, 99),
        "final_position_error_median": percentile((r.score.position_error for r in ok), 50),
        "final_position_error_p90": percentile((r.score.position_error for r in ok), 90),
        "final_heading_error_deg_median": percentile(
            (np.degrees(r.score.heading_error) for r in ok), 50),
        "final_heading_error_deg_p90": percentile(
            (np.degrees(r.score.heading_error) for r in ok), 90),
    }


def write_json(path: Path | None, payload: dict[str, Any]) -> None:
    if path is not None:
        path.write_text(json.dumps(payload, indent=1))
        print(f"results written to {path}")


def fmt(value: Any, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)
