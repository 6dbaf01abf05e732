"""Benchmarks over a family of surfaces (`objects`, `profile`): B2's noise on each surface,
one row per surface and per family.

An episode that raises is kept as an error (its message in the JSON) and the benchmark
goes on; an undeclared run is "not yet"; a wrong declaration is the one failure that
matters most, so it is printed in capitals, listed by surface and seed, drawn in red, and
makes the command exit with status 1.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.episode.simulate import EpisodeReport
from service.errors import ConfigError
from service.localization.map_check import check_map
from service.localization.maps import load_map
from service.localization.presets import SIZES
from tools.arg_types import number
from tools.bench_common import (
    B2_DEFAULTS,
    check_bench_args,
    collect,
    executor_for,
    fmt,
    percentile,
    write_json,
)
from tools.executor import Failed, Outcome
from tools.scenario_options import settings_from_args

TARGET_SUCCESS = 0.9
"""Issue 9: at least 90 % within 60 steps on every surface one feature disambiguates."""
TARGET_P99_MS = 5.0


def add_surface_options(p: argparse.ArgumentParser, *, families: str, seeds: str,
                        size: float, runs: int) -> None:
    from tools.bench_common import add_bench_options

    add_bench_options(p, defaults=B2_DEFAULTS, runs=runs, own_maps=True)
    p.add_argument("--families", default=families, metavar="NAME,...",
                   help="surface families, comma separated (default: %(default)s)")
    p.add_argument("--map-seeds", default=seeds, metavar="N,...",
                   help="seeds of the surfaces of each family (default: %(default)s)")
    p.add_argument("--size", type=number(*SIZES, "units of 10 mm"), default=size, metavar="UNITS",
                   help="side (or length) of each surface in units of 10 mm "
                        "(default: %(default)s)")


def seeds_from(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ConfigError(f"--map-seeds takes whole numbers separated by commas, "
                          f"got '{text}'") from None
    if not seeds or min(seeds) < 0:
        raise ConfigError(f"--map-seeds needs at least one seed >= 0, got '{text}'")
    return seeds


def families_from(text: str, allowed: Sequence[str]) -> list[str]:
    families = [f.strip() for f in text.split(",") if f.strip()]
    unknown = [f for f in families if f not in allowed]
    if not families or unknown:
        raise ConfigError(f"--families takes names from {', '.join(allowed)}, got '{text}'")
    return families


def surface_row(name: str, outcomes: Sequence[Outcome]) -> dict[str, Any]:
    """The per-surface (or per-family) figures the issue asks for."""
    done = [o for o in outcomes if isinstance(o, EpisodeReport)]
    failed = [o for o in outcomes if isinstance(o, Failed)]
    steps = [len(r.result.steps) for r in done]
    later = [s.compute_ms for r in done for s in r.result.steps[1:]]
    wrong = [r for r in done if r.score.wrong_declaration]
    success = sum(r.score.success for r in done)
    not_yet = sum(not r.result.converged for r in done)
    return {
        "surface": name, "runs": len(outcomes), "successes": int(success),
        "wrong_declarations": len(wrong), "not_yet": int(not_yet), "errors": len(failed),
        "steps_median": percentile(steps, 50), "steps_p90": percentile(steps, 90),
        "compute_ms_first_median": percentile(
            (r.result.steps[0].compute_ms for r in done if r.result.steps), 50),
        "compute_ms_after_first_p99": percentile(later, 99),
        "compute_ms_after_first_median": percentile(later, 50),
        "background_ms_p99": percentile(
            (s.background_ms for r in done for s in r.result.steps), 99),
        "wrong_runs": [{"map": r.settings.map, "seed": r.settings.seed,
                        "position_error": r.score.position_error,
                        "heading_error_deg": float(np.degrees(r.score.heading_error))}
                       for r in wrong],
        "error_runs": [{"map": f.settings.map, "seed": f.settings.seed, "error": f.error}
                       for f in failed],
        "verdict": verdict(len(outcomes), int(success), len(wrong), len(failed)),
    }


def verdict(runs: int, success: int, wrong: int, errors: int) -> str:
    if wrong:
        return "WRONG"
    if errors:
        return "errors"
    return "ok" if success >= TARGET_SUCCESS * runs else "not yet"


HEADER = (f"{'surface':<26} {'localized':>9} {'not yet':>7} {'WRONG':>5} {'errors':>6} "
          f"{'steps med/p90':>13} {'first ms':>8} {'p99 after':>9} {'between':>7}  verdict")


def print_row(r: dict[str, Any]) -> None:
    steps = f"{fmt(r['steps_median'], 'g')}/{fmt(r['steps_p90'], 'g')}"
    mark = "  <-- WRONG" if r["wrong_declarations"] else ""
    print(f"{r['surface']:<26} {r['successes']:>4}/{r['runs']:<4} {r['not_yet']:>7} "
          f"{r['wrong_declarations']:>5} {r['errors']:>6} {steps:>13} "
          f"{fmt(r['compute_ms_first_median']):>8} {fmt(r['compute_ms_after_first_p99']):>9} "
          f"{fmt(r['background_ms_p99']):>7}  {r['verdict']}{mark}", flush=True)


def run_families(args: argparse.Namespace, *, scenario: str, label: str,
                 allowed: Sequence[str], spec: str) -> int:
    """`run_surfaces` over --families x --map-seeds, each map named by `spec`, a format
    with {family}, {size} and {seed}."""
    families = families_from(args.families, allowed)
    seeds = seeds_from(args.map_seeds)
    surfaces = {f: [spec.format(family=f, size=f"{args.size:g}", seed=seed) for seed in seeds]
                for f in families}
    return run_surfaces(args, scenario=scenario, label=label, surfaces=surfaces)


def run_surfaces(args: argparse.Namespace, *, scenario: str, label: str,
                 surfaces: dict[str, list[str]]) -> int:
    """Run `args.runs` seeded episodes on every surface ({family: [map specs]}), print a row
    per surface and per family, write JSON and a figure; status 1 on a wrong declaration."""
    check_bench_args(args)
    if args.map != B2_DEFAULTS.map or args.spacing is not None:
        raise ConfigError(f"{scenario} builds its own surfaces: --map and --spacing do not "
                          "apply (see "
                          "--families, --map-seeds, --size; `haptic bench realistic --map "
                          "FILE` runs your map)")
    base = settings_from_args(args, noise=True)
    specs = [spec for family in surfaces.values() for spec in family]
    maps = {spec: load_map(spec) for spec in specs}
    for spec, height_map in maps.items():
        for warning in check_map(height_map, base.radius, base.step).warnings:
            if "repeats" not in warning:  # near symmetries are these families' point
                print(f"warning: {spec}: {warning}")
    settings = [dataclasses.replace(base, map=spec, seed=args.first_seed + i)
                for spec in specs for i in range(args.runs)]
    runs = f"{args.runs} run{'s' if args.runs != 1 else ''}"
    print(f"{label}: {base.algorithm} + {base.policy}, B2's noise, {runs} on each "
          f"of {len(specs)} surfaces, at most {base.max_steps} steps")
    with executor_for(args) as executor:
        outcomes = collect(executor, settings, maps, desc=label)
    by_map = {spec: [o for o in outcomes if o.settings.map == spec] for spec in specs}
    print(HEADER)
    rows = []
    for spec in specs:
        rows.append(surface_row(spec, by_map[spec]))
        print_row(rows[-1])
    family_rows = [surface_row(f"{family} (all)", [o for spec in family_specs
                                                    for o in by_map[spec]])
                   for family, family_specs in surfaces.items()]
    total = surface_row("all surfaces", outcomes)
    print("-" * len(HEADER))
    for r in [*family_rows, total]:
        print_row(r)
    _print_verdicts(rows, total)
    write_json(args.json, {"scenario": scenario, "settings": base.to_json(),
                           "surfaces": rows, "families": family_rows, "total": total,
                           **executor.info(),
                           "targets": {"wrong_declarations": 0,
                                       "success_where_one_feature_decides": TARGET_SUCCESS,
                                       "compute_ms_after_first_p99": TARGET_P99_MS},
                           "runs": [o.to_json() for o in outcomes]})
    if args.plot:
        title = (f"{label}: {base.algorithm} + {base.policy}, B2's noise, {args.runs} runs "
                 "per surface")
        plot_rows(rows + family_rows, args.plot, title=title)
        print(f"figure written to {args.plot}")
    return 1 if total["wrong_declarations"] else 0


def _print_verdicts(rows: list[dict[str, Any]], total: dict[str, Any]) -> None:
    if total["wrong_declarations"]:
        where = "; ".join(f"{w['map']} seed {w['seed']} ({w['position_error'] * 1e3:.1f} mm, "
                          f"{w['heading_error_deg']:.1f} deg off)"
                          for r in rows for w in r["wrong_runs"])
        print(f"WRONG DECLARATIONS: {total['wrong_declarations']}: {where}")
    else:
        print("wrong declarations: none")
    if total["errors"]:
        first = next(e for r in rows for e in r["error_runs"])
        print(f"errors: {total['errors']} episodes raised, e.g. {first['map']} seed "
              f"{first['seed']}: {first['error']}")
    undecided = [r["surface"] for r in rows if r["verdict"] == "not yet"]
    if undecided:
        print(f"not yet (under {TARGET_SUCCESS:.0%} localized, no wrong declaration): "
              f"{', '.join(undecided)}")


def plot_rows(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Outcomes per surface (stacked bars, wrong declarations in red), steps, compute."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    names = [r["surface"] for r in rows]
    y = np.arange(len(rows))[::-1]
    fig, axes = plt.subplots(1, 3, figsize=(14, 0.35 * len(rows) + 3), sharey=True,
                             gridspec_kw={"width_ratios": [2, 1.2, 1.2]})
    left = np.zeros(len(rows))
    for key, colour, label in (("successes", "tab:green", "localized"),
                               ("not_yet", "0.75", "not yet (no declaration)"),
                               ("errors", "k", "episode raised"),
                               ("wrong_declarations", "red", "WRONG declaration")):
        share = np.array([r[key] / r["runs"] for r in rows])
        axes[0].barh(y, share, left=left, color=colour, label=label)
        left += share
    for yi, r in zip(y, rows, strict=True):
        if r["wrong_declarations"]:
            axes[0].text(1.01, yi, f"{r['wrong_declarations']} WRONG", color="red",
                         va="center", fontsize=8, fontweight="bold")
    axes[0].axvline(TARGET_SUCCESS, color="tab:green", ls=":", lw=1,
                    label=f"target: {TARGET_SUCCESS:.0%} localized")
    axes[0].set(xlim=(0, 1.2), xlabel="share of runs", title="outcome per surface")
    axes[0].set_yticks(y, names, fontsize=8)
    med = [r["steps_median"] or 0 for r in rows]
    p90 = [r["steps_p90"] or 0 for r in rows]
    axes[1].barh(y, p90, color="tab:blue", alpha=0.35, label="p90")
    axes[1].barh(y, med, color="tab:blue", label="median")
    axes[1].set(xlabel="steps (all runs)", title="steps")
    axes[2].barh(y, [r["compute_ms_after_first_p99"] or 0 for r in rows], color="tab:purple",
                 label="p99 after the first step")
    axes[2].plot([r["compute_ms_first_median"] or 0 for r in rows], y, "k|", ms=10, mew=2,
                 label="first step (median)")
    axes[2].axvline(TARGET_P99_MS, color="grey", ls=":", label=f"target: p99 {TARGET_P99_MS:g} ms")
    axes[2].set(xlabel="ms per update", title="localizer compute", xscale="log")
    axes[2].xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axes[2].xaxis.set_major_formatter(ScalarFormatter())
    axes[2].xaxis.set_minor_formatter(NullFormatter())
    for ax in axes:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2,
                  frameon=False)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
