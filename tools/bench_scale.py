"""B3 `scale`: compute per step as the map grows (BENCHMARKS.md B3).

Seeded smooth random bumps (`bumps:SIZE:SEED`) of 20, 40 and 80 units at 10 samples per
unit, with B2's noise; one row per algorithm and map size. A bounded-pool localizer
(Algorithm IV) should stay flat after its first step; a table over every pose
(Algorithm III) grows with the area.
"""

from __future__ import annotations

import argparse

import numpy as np

from service.errors import ConfigError
from service.localization.maps import load_map
from service.localization.presets import SIZES
from service.registry import LOCALIZERS
from tools.arg_types import integer
from tools.bench_common import B2_DEFAULTS as DEFAULTS
from tools.bench_common import (
    add_bench_options,
    check_bench_args,
    executor_for,
    fmt,
    run_episodes,
    summarize,
    write_json,
)
from tools.executor import Executor
from tools.scenario_options import settings_from_args

COMPARED = ("particles", "elimination")
TARGET_P99_MS = 5.0
"""The issue's bound on Algorithm IV's p99 per step after the first, drawn on the figure."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bench_options(p, defaults=DEFAULTS, runs=20, workers=1,
                      algorithm_help=f"default: compare {' and '.join(COMPARED)}",
                      own_maps=True)
    p.set_defaults(algorithm=None)  # none given: compare Algorithms IV and III
    p.add_argument("--sizes", default="20,40,80", metavar="UNITS,...",
                   help="map sizes in units, comma separated (default: %(default)s)")
    p.add_argument("--map-seed", type=integer(0, 2**63 - 1), default=1,
                   help="seed of the bumps maps (default: %(default)s)")


def _sizes(text: str) -> list[float]:
    try:
        sizes = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ConfigError(f"--sizes takes numbers separated by commas, got '{text}'") from None
    if not sizes:
        raise ConfigError("--sizes needs at least one size")
    bad = [s for s in sizes if not SIZES[0] <= s <= SIZES[1]]  # nan too
    if bad:
        raise ConfigError(f"--sizes must each be {SIZES[0]:g}..{SIZES[1]:g} units, got "
                          f"{', '.join(f'{s:g}' for s in bad)}")
    return sizes


def run(args: argparse.Namespace) -> int:
    check_bench_args(args)
    sizes = _sizes(args.sizes)
    algorithms = [args.algorithm] if args.algorithm else list(COMPARED)
    for name in algorithms:
        LOCALIZERS.load(name)
    if args.map != DEFAULTS.map or args.spacing is not None:
        raise ConfigError("B3 builds its own bumps maps: --map and --spacing do not apply "
                          "(see --sizes, "
                          "--map-seed; `haptic bench realistic --map FILE` runs your map)")
    rows = []
    executor = executor_for(args)
    if executor.workers > 1:
        print(f"note: {executor.workers} workers share the machine, so the compute per step "
              "below includes their contention; B3's reference is --workers 1")
    with executor:
        _run_sizes(args, sizes, algorithms, executor, rows)
    write_json(args.json, {"scenario": "scale", "settings": settings_from_args(
        args, algorithm=algorithms[0], noise=True).to_json(), "rows": rows, **executor.info()})
    if args.plot:
        plot_rows(rows, args.plot)
        print(f"figure written to {args.plot}")
    return 0


def _run_sizes(args: argparse.Namespace, sizes: list[float], algorithms: list[str],
               executor: Executor, rows: list[dict]) -> None:
    for size in sizes:
        spec = f"bumps:{size:g}:{args.map_seed}"
        height_map = load_map(spec)
        for name in algorithms:
            settings = [settings_from_args(args, map=spec, algorithm=name, noise=True,
                                           seed=args.first_seed + i) for i in range(args.runs)]
            reports = run_episodes(settings, height_map, desc=f"B3 {name} {size:g}",
                                   executor=executor)
            s = summarize(reports)
            rows.append({
                "algorithm": name, "policy": settings[0].policy, "map": spec,
                "map_units": size, "runs": s["runs"], "successes": s["successes"],
                "wrong_declarations": s["wrong_declarations"],
                "steps": s["steps_median"], "steps_median": s["steps_median"],
                "compute_ms_first_median": s["compute_ms_first_median"],
                "compute_ms_median": s["compute_ms_median"],
                "compute_ms_p99": s["compute_ms_p99"],
                "compute_ms_after_first_median": s["compute_ms_after_first_median"],
                "compute_ms_after_first_p99": s["compute_ms_after_first_p99"],
                "background_ms_p99": s["background_ms_p99"],
            })
            print_row(rows[-1])


def print_row(r: dict) -> None:
    print(f"{r['algorithm']:<12} {r['map_units']:>4g} units  {r['successes']:>3}/{r['runs']:<3} "
          f"ok  wrong {r['wrong_declarations']}  steps {fmt(r['steps'], 'g'):>4}  compute "
          f"first {fmt(r['compute_ms_first_median']):>8} ms  after it median "
          f"{fmt(r['compute_ms_after_first_median']):>7} ms, p99 "
          f"{fmt(r['compute_ms_after_first_p99']):>7} ms; between steps p99 "
          f"{fmt(r['background_ms_p99']):>6} ms", flush=True)


def plot_rows(rows: list[dict], path) -> None:
    """Per map size and algorithm: compute per step after the first, and the outcomes."""
    from matplotlib.figure import Figure

    from tools.plots import plain_log_ticks

    fig = Figure(figsize=(13, 5.0))
    ax, ok_ax = fig.subplots(1, 2, width_ratios=(1.25, 1))
    names = list(dict.fromkeys(r["algorithm"] for r in rows))
    colour = {name: f"C{i}" for i, name in enumerate(names)}
    for name in names:
        mine = [r for r in rows if r["algorithm"] == name]
        units = [r["map_units"] for r in mine]
        for key, style in (("compute_ms_after_first_median", "-o"),
                           ("compute_ms_after_first_p99", "--^")):
            ax.plot(units, [r[key] or 0 for r in mine], style, color=colour[name],
                    label=f"{name} {key.rsplit('_', 1)[-1]}")
    ax.axhline(TARGET_P99_MS, color="grey", linewidth=0.8, linestyle=":",
               label=f"target: Algorithm IV p99 <= {TARGET_P99_MS:g} ms")
    ax.set(xlabel="map size (units of 10 mm)", ylabel="ms per step after the first",
           yscale="log", title="compute per step as the map grows")
    plain_log_ticks(ax.yaxis)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
    sizes = sorted({r["map_units"] for r in rows})
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        mine = {r["map_units"]: r for r in rows if r["algorithm"] == name}
        x = np.arange(len(sizes)) + (i - (len(names) - 1) / 2) * width
        ok = [100 * mine[u]["successes"] / mine[u]["runs"] if u in mine else 0 for u in sizes]
        wrong = [100 * mine[u]["wrong_declarations"] / mine[u]["runs"] if u in mine else 0
                 for u in sizes]
        bars = ok_ax.bar(x, ok, width, color=colour[name], label=f"{name}: localized")
        ok_ax.bar(x, wrong, width, bottom=ok, color="tab:red",
                  label="wrong pose declared" if i == 0 else None)
        ok_ax.bar_label(bars, labels=[f"{v:.0f}%" for v in ok], fontsize=7)
    ok_ax.set_xticks(np.arange(len(sizes)), [f"{u:g}" for u in sizes])
    ok_ax.set(xlabel="map size (units of 10 mm)", ylabel="% of runs", ylim=(0, 112),
              title="success (the rest: not yet localized)")
    ok_ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
    fig.suptitle(f"B3: bumps maps, {rows[0]['runs']} runs per size and algorithm")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
