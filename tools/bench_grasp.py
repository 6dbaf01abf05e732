"""B6 `grasp`: a hand holds, localizes and explores an object without dropping it
(BENCHMARKS.md B6, paper §6).

For each hand (two and three fingers) and object family, `--runs` seeded runs at B2-level
noise; run i holds family member NAME:i (held-out shapes, not one preset) with seed i; an
object of one's own (a preset NAME:SEED or an outline or mesh file) is held in every run,
seed i hiding its start pose. Each
run is repeated with the hand's first finger alone on the same contour, the object clamped
(the steps a single finger needs), and without the grasp gate (the ablation: its drops are
what the gate prevents). The episodes run where every benchmark's do (`tools.executor`: a
local pool, one worker per core by default, or a Dask cluster). Each drop and wrong
declaration of a gated run is listed, and either gives exit status 1.
"""

from __future__ import annotations

import argparse
import math
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.errors import ConfigError, ServiceError
from service.localization.objects.files import OBJECT_FILE_SUFFIXES
from service.localization.surface import HeightMap
from tools.arg_types import integer, number
from tools.bench_common import (
    check_seeds,
    executor_for,
    fmt,
    percentile,
    progress,
    write_json,
)
from tools.executor import Failed, add_executor_options
from tools.outputs import check_outputs

OBJECTS = ("ellipse", "rounded", "blob", "keyed")
HANDS = ("two-finger", "three-finger")
TARGETS = {"drops": "0", "wrong_declarations": "0",
           "successes": ">= 95 % on rounded, blob, keyed",
           "compute_ms_after_first_p99": "<= 5 ms"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=int, default=100, help="runs per hand and object "
                   "(default: %(default)s)")
    p.add_argument("--first-seed", type=int, default=0, help="seed (and family member) of the "
                   "first run")
    p.add_argument("--objects", default=",".join(OBJECTS),
                   help="object families, comma-separated (default: %(default)s), or objects "
                        "of one's own (NAME:SEED, an outline .csv or a mesh cut at its "
                        "centroid's z), each held in every run")
    p.add_argument("--hands", default=",".join(HANDS),
                   help="hands, comma-separated (default: %(default)s)")
    p.add_argument("--plane", metavar="AXIS=V|PX,PY,PZ,NX,NY,NZ",
                   help="where every mesh in --objects is cut (as `haptic run --plane`); "
                        "default: z through each mesh's centroid")
    p.add_argument("--object-units", choices=("m", "mm"), default="m",
                   help="units of every object file in --objects (default: %(default)s)")
    p.add_argument("--max-steps", type=integer(1, 10_000), default=60,
                   help="(default: %(default)s)")
    p.add_argument("--start-quality", type=number(0.0, 1000.0, "N"), metavar="N",
                   help="grasp quality (newtons) "
                   "every hand starts with at least; the policy relies on it (default: the "
                   "threshold)")
    p.add_argument("--no-ablation", action="store_true", help="skip the runs without the gate")
    p.add_argument("--no-single", action="store_true", help="skip the single-finger runs")
    p.add_argument("--json", type=Path, metavar="FILE", help="write results as JSON")
    p.add_argument("--plot", type=Path, metavar="FILE.png", help="write a figure")
    add_executor_options(p)


def _check(args: argparse.Namespace) -> None:
    if args.runs < 1 or args.max_steps < 1:
        raise ConfigError("--runs and --max-steps must be at least 1")
    check_seeds(args.first_seed, args.runs)
    check_outputs(args.json, figures=(args.plot,))
    from firmware_if.errors import HandConfigError
    from firmware_if.hand import load_hand
    from service.errors import ObjectError
    from service.localization.objects.files import load_object

    for hand in args.hands.split(","):  # before any episode (one raised it, exit 1)
        try:
            load_hand(hand, holding=True)
        except HandConfigError as exc:
            raise ConfigError(f"--hands: {exc}") from None
    if args.plane is not None and not any(_plane_for(name, args.plane)
                                          for name in args.objects.split(",")):
        raise ConfigError("--plane cuts mesh files (.stl, .obj, .ply) of --objects, and "
                          "none is one")  # as `haptic run --plane` refuses an outline
    if args.object_units != "m" and all(name in OBJECTS for name in args.objects.split(",")):
        raise ConfigError("--object-units applies to object files of --objects, and none is "
                          "one: the families are in metres")  # it was ignored
    for name in args.objects.split(","):
        if name in OBJECTS:
            continue
        try:
            load_object(name, plane=_plane_for(name, args.plane), units=args.object_units)
        except ObjectError as exc:
            raise ConfigError(f"--objects: '{name}' is neither a family ("
                              f"{', '.join(OBJECTS)}) nor an object: {exc}") from None


def _check_holds(jobs: Sequence[tuple[tuple[str, str, str], Any]]) -> None:
    """Refuse, before any episode, a hand that cannot hold an object: one finger, or no
    hold at the first seed's start (out of reach, too big or too slippery). A held-out
    check's bench ran half its episodes first, then exited 1, the status of a drop, and
    wrote nothing."""
    from service.episode.hand_episode import seeded_world
    from service.episode.hand_scenario import load_parts

    seen: set[tuple[str, str]] = set()
    refused: list[str] = []
    for (hand, family, kind), settings in jobs:
        if kind != "gated" or (hand, family) in seen:
            continue
        seen.add((hand, family))
        try:
            seeded_world(settings, load_parts(settings))
        except ConfigError as exc:
            refused.append(f"--hands {hand} --objects {family}: {exc}")
    if refused:  # every pair that cannot hold, at once: a lab mends them in one go
        firmer = jobs[0][1].start_n is not None
        # the advice of `haptic run`'s names options the bench does not take
        raise ConfigError(
            f"{len(refused)} of {len(seen)} hand-object pairs cannot be held, so nothing ran: "
            + "; ".join(refused) + ". Leave them out of --hands/--objects"
            + (", or ask less of the start (--start-quality)" if firmer else "")
            + (" (the bench runs the defaults of --mass, --mu and --threshold: try others "
               "with `haptic run --hand H --object O`)"
               if any("found no hold" in r for r in refused) else ""))


_PARTS: dict[tuple, Any] = {}


def episode(settings, maps: dict[str, HeightMap] | None = None) -> dict[str, Any]:
    """One episode's outcome, small enough to send between processes (an executor's task:
    a hand needs no map)."""
    from service.episode.hand_episode import simulate_hand
    from service.episode.hand_scenario import load_parts

    key = (settings.object, settings.hand, settings.single_finger)
    if key not in _PARTS:
        if len(_PARTS) > 64:
            _PARTS.clear()
        _PARTS[key] = load_parts(settings)
    report = simulate_hand(settings, _PARTS[key])
    steps = report.result.steps
    return {"object": settings.object, "seed": settings.seed,
            "success": report.score.success, "wrong": report.score.wrong_declaration,
            "dropped": report.result.dropped, "stuck": report.result.stuck,
            "converged": report.result.converged, "steps": len(steps),
            "manipulations": sum(s.kind == "manipulate" for s in steps),
            "min_quality": report.min_quality,
            "position_error": report.score.position_error,
            "heading_error_deg": (None if report.score.heading_error is None
                                  else math.degrees(report.score.heading_error)),
            "compute_ms_after_first": [s.compute_ms for s in steps[1:] if s.compute_ms > 0],
            "policy_ms": [s.policy_ms for s in steps],
            "settle_ms": [s.settle_ms for s in steps if s.settle_ms > 0]}


def _summary(outcomes: Sequence[dict[str, Any]]) -> dict[str, Any]:
    later = [ms for o in outcomes for ms in o["compute_ms_after_first"]]
    quality = [o["min_quality"] for o in outcomes if math.isfinite(o["min_quality"])]
    return {
        "runs": len(outcomes),
        "successes": int(sum(o["success"] for o in outcomes)),
        "wrong_declarations": int(sum(o["wrong"] for o in outcomes)),
        "drops": int(sum(o["dropped"] for o in outcomes)),
        "stuck": int(sum(o["stuck"] for o in outcomes)),
        "steps_median": float(np.median([o["steps"] for o in outcomes])),
        # the runs that localized only: a median over runs that mostly stop at step 0
        # (two fingers) reads 0 beside those that took 14 steps to localize
        "steps_median_localized": percentile([o["steps"] for o in outcomes if o["success"]],
                                             50),
        "manipulations_mean": float(np.mean([o["manipulations"] for o in outcomes])),
        "quality_min": min(quality) if quality else None,
        "compute_ms_after_first_median": percentile(later, 50),
        "compute_ms_after_first_p99": percentile(later, 99),
        "policy_ms_p99": percentile([ms for o in outcomes for ms in o["policy_ms"]], 99),
        "settles": int(sum(len(o["settle_ms"]) for o in outcomes)),
        "settle_ms_p99": percentile([ms for o in outcomes for ms in o["settle_ms"]], 99),
    }


def run(args: argparse.Namespace) -> int:
    from service.episode.hand_scenario import HandSettings

    _check(args)
    families = args.objects.split(",")
    hands = args.hands.split(",")
    seeds = range(args.first_seed, args.first_seed + args.runs)
    kinds = ["gated"] + ([] if args.no_ablation else ["ablation"]) + (
        [] if args.no_single else ["single"])
    jobs = []
    for hand in hands:
        for family in families:
            for kind in kinds:
                for seed in seeds:
                    jobs.append(((hand, family, kind), HandSettings(
                        object=f"{family}:{seed}" if family in OBJECTS else family,
                        hand=hand, seed=seed, noise=True,
                        max_steps=args.max_steps, gate=kind != "ablation",
                        single_finger=kind == "single", start_n=args.start_quality,
                        plane=_plane_for(family, args.plane),
                        units="m" if family in OBJECTS else args.object_units)))
    # a bad hand name or start quality fails here, not in a worker
    HandSettings(hand=hands[0], start_n=args.start_quality)
    _check_holds(jobs)
    outcomes: list[dict[str, Any] | None] = [None] * len(jobs)
    with executor_for(args) as executor, progress(len(jobs), "B6 grasp") as bar:
        for index, outcome in executor.run([s for _, s in jobs], {}, task=episode):
            if isinstance(outcome, Failed):
                if outcome.refused:  # the user's to fix, as up front (exit status 2)
                    raise ConfigError(f"--hand {outcome.settings.hand} --object "
                                      f"{outcome.settings.object} --seed "
                                      f"{outcome.settings.seed}: {outcome.error}")
                raise ServiceError(f"an episode raised: --hand {outcome.settings.hand} "
                                   f"--object {outcome.settings.object} --seed "
                                   f"{outcome.settings.seed}: {outcome.error}")
            outcomes[index] = outcome
            bar.update()
        info = executor.info()
    results: dict[tuple, list[dict[str, Any]]] = {}
    for (key, _), outcome in zip(jobs, outcomes, strict=True):
        results.setdefault(key, []).append(outcome)  # in seed order, whoever ran it
    # keyed HAND/OBJECT/KIND, and each says its own: a hand or object file's path has "/" too
    table = {f"{hand}/{family}/{kind}": {"hand": hand, "object": family, "kind": kind,
                                         **_summary(results[(hand, family, kind)])}
             for hand in hands for family in families for kind in kinds}
    gated = [o for (h, f, k), v in results.items() if k == "gated" for o in v]
    summary = _summary(gated)
    summary["quality_min_run"] = _least_quality_run(results, args.max_steps,
                                                    args.start_quality, _object_flags(args))
    if "ablation" in kinds:
        summary["ablation_drops"] = int(sum(o["dropped"] for (_, _, k), v in results.items()
                                            if k == "ablation" for o in v))
    _print(table, summary, hands, families, kinds)
    failures = failed_runs(results, args.max_steps, args.start_quality, _object_flags(args))
    for line in failures:
        print(line)
    write_json(args.json, {"scenario": "grasp", "targets": TARGETS,
                           "start_quality_n": args.start_quality, "summary": summary,
                           "table": table, **info,
                           "runs": {"/".join(k): v for k, v in results.items()}})
    if args.plot:
        grasp_figure(table, hands, families, kinds, args.plot)
        print(f"figure written to {args.plot}")
    return 1 if failures else 0


def _plane_for(spec: str, plane: str | None) -> str | None:
    """--plane for a mesh of --objects (a preset or an outline is not cut)."""
    from service.localization.objects.files import MESH_SUFFIXES

    return plane if Path(spec).suffix.lower() in MESH_SUFFIXES else None


def _object_flags(args: argparse.Namespace) -> dict[str, str]:
    """`haptic run` options an object file of this bench was read with."""
    flags = {} if args.object_units == "m" else {"--object-units": args.object_units}
    if args.plane is not None:
        flags["--plane"] = args.plane
    return flags


def failed_runs(results: dict[tuple, list[dict[str, Any]]], max_steps: int,
                start_n: float | None = None, object_flags: dict[str, str] | None = None
                ) -> list[str]:
    """A line for each gated run that dropped the object or declared a wrong pose (the
    ablation's drops are what it is for), with the `haptic run` options that re-run it."""
    lines = []
    for (hand, _, kind), outcomes in results.items():
        if kind != "gated":
            continue
        for o in outcomes:
            where = _rerun_options(hand, o, max_steps, start_n, object_flags)
            if o["dropped"]:
                lines.append(f"DROPPED: {where} at step {o['steps']} (least quality "
                             f"{o['min_quality']:.2f} N)")
            if o["wrong"]:
                lines.append(f"WRONG: {where} ({o['position_error'] * 1e3:.1f} mm, "
                             f"{o['heading_error_deg']:.1f} deg off)")
    return lines


def _least_quality_run(results: dict[tuple, list[dict[str, Any]]], max_steps: int,
                       start_n: float | None, object_flags: dict[str, str] | None = None
                       ) -> str | None:
    """The `haptic run` options of the gated run whose grasp came nearest the margin: the
    table's column says how near, this says which run to look at."""
    runs = [(o["min_quality"], hand, o) for (hand, _, kind), outcomes in results.items()
            if kind == "gated" for o in outcomes if math.isfinite(o["min_quality"])]
    if not runs:
        return None
    _, hand, o = min(runs, key=lambda r: r[0])
    return _rerun_options(hand, o, max_steps, start_n, object_flags)


def _rerun_options(hand: str, outcome: dict[str, Any], max_steps: int,
                   start_n: float | None, object_flags: dict[str, str] | None = None) -> str:
    """The `haptic run` options that re-run a gated run as it ran (a helper re-ran one
    without `--noise` and saw it localize), an object file's own options with it."""
    spec = outcome["object"]
    flags = {k: v for k, v in (object_flags or {}).items()
             if Path(spec).suffix.lower() in OBJECT_FILE_SUFFIXES
             and (k != "--plane" or _plane_for(spec, v) is not None)}
    return (f"--hand {_rerunnable(hand)} --object {_rerunnable(spec)} "
            f"--seed {outcome['seed']} --noise --max-steps {max_steps}") + (
        "" if start_n is None else f" --start-quality {start_n:g}") + "".join(
        f" {k} {shlex.quote(v)}" for k, v in flags.items())


def _rerunnable(spec: str) -> str:
    """A hand or object as a failure line names it: a file by its absolute path (quoted
    for the shell where it needs it), so the line re-runs from any folder; a preset as
    given. A held-out check's relative paths re-ran only from the folder it ran in."""
    path = Path(spec)
    return shlex.quote(str(path.resolve())) if path.is_file() else spec


def _print(table: dict, summary: dict, hands, families, kinds) -> None:
    print("B6 grasp: hand, object family, runs; success, wrong, drops, stuck, steps median "
          "(in brackets: one finger, the object clamped) over all runs and over those "
          "localized, least quality, compute after the first step median/p99")
    # files by their stems, in columns as wide as the longest (paths broke the columns)
    hand_width = max(13, *(len(_short(h)) for h in hands))
    family_width = max(8, *(len(_short(f)) for f in families))
    for hand in hands:
        for family in families:
            g = table[f"{hand}/{family}/gated"]
            single = table.get(f"{hand}/{family}/single")
            ablation = table.get(f"{hand}/{family}/ablation")
            print(f"  {_short(hand):<{hand_width}} {_short(family):<{family_width}} "
                  f"{g['runs']:4d}  ok {g['successes']:4d}  "
                  f"wrong {g['wrong_declarations']}  drops {g['drops']}  stuck {g['stuck']}  "
                  f"steps {fmt(g['steps_median'], 'g')}"
                  f" ({fmt(single and single['steps_median'], 'g')}), localized in "
                  f"{fmt(g['steps_median_localized'], 'g')}"
                  f" ({fmt(single and single['steps_median_localized'], 'g')})  "
                  f"quality >= {fmt(g['quality_min'])} N  "
                  f"{fmt(g['compute_ms_after_first_median'])}/"
                  f"{fmt(g['compute_ms_after_first_p99'])} ms"
                  + (f"  | no gate: drops {ablation['drops']}" if ablation else ""))
    print(f"all gated runs: {summary['runs']} runs, {summary['successes']} successes, "
          f"{summary['wrong_declarations']} wrong, {summary['drops']} drops; compute after "
          f"the first step p99 {fmt(summary['compute_ms_after_first_p99'])} ms; the check "
          f"of the whole object before a declaration, between update and move, "
          f"{summary['settles']} times, p99 {fmt(summary['settle_ms_p99'])} ms"
          + (f"; without the gate {summary['ablation_drops']} drops"
             if "ablation_drops" in summary else ""))
    if summary.get("quality_min_run"):
        print(f"least quality {fmt(summary['quality_min'])} N: {summary['quality_min_run']}")


def grasp_figure(table: dict, hands, families, kinds, path: Path) -> None:
    """Per hand and object: the share of runs that localized, dropped or declared wrongly,
    and the median steps. Bars run across, a row per pair, and the figure grows with the
    rows: a held-out lab's 16 pairs, as columns, ran their labels into one another."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # files by their stems, presets whole: a held-out check's file objects' paths ran
    # into one another, and "three-finger" read "three"
    labels = [f"{_short(h)} · {_short(f)}" for h in hands for f in families]
    y = np.arange(len(labels))
    fig, axes = plt.subplots(1, 2, figsize=(12, max(3.5, 1.6 + 0.42 * len(labels))),
                             sharey=True)
    rows = [table[f"{h}/{f}/gated"] for h in hands for f in families]
    runs = np.array([r["runs"] for r in rows], dtype=float)
    bars = [("successes", "tab:green", 1.0, "localized"), ("drops", "tab:red", 1.0, "drops"),
            ("wrong_declarations", "black", 1.0, "wrong declarations")]
    columns = [np.array([r[key] for r in rows]) / runs * 100 for key, *_ in bars]
    if "ablation" in kinds:
        bars.append(("ablation", "tab:red", 0.35, "drops without the gate"))
        columns.append(np.array([table[f"{h}/{f}/ablation"]["drops"] for h in hands
                                 for f in families]) / runs * 100)
    height = 0.8 / len(bars)
    for i, ((_, colour, alpha, label), values) in enumerate(zip(bars, columns, strict=True)):
        axes[0].barh(y + (i - (len(bars) - 1) / 2) * height, values, height, color=colour,
                     alpha=alpha, label=label)
    axes[0].set_yticks(y, labels, fontsize=8)
    axes[0].invert_yaxis()  # the first pair on top, as in the printed table
    axes[0].set(xlabel="% of runs", xlim=(0, 100), title="B6: localized, drops and wrong "
                "declarations")
    axes[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4)
    steps = np.array([r["steps_median"] for r in rows], dtype=float)
    axes[1].barh(y - 0.2, steps, 0.4, label="hand (gated)")
    values = [steps]
    if "single" in kinds:
        single = np.array([table[f"{h}/{f}/single"]["steps_median"] for h in hands
                           for f in families], dtype=float)
        axes[1].barh(y + 0.2, single, 0.4, label="one finger, object clamped")
        values.append(single)
    for offset, v in zip((-0.2, 0.2), values, strict=False):  # 0 (stuck at once) shows too
        for yi, n in zip(y, v, strict=True):
            axes[1].text(n, yi + offset, f" {n:g}", va="center", fontsize=7)
    axes[1].set(xlabel="steps", title="median steps taken\n(a run that ends undeclared "
                "counts where it ended)")
    axes[1].set_xlim(0, 1.15 * max(float(np.max(np.concatenate(values))), 1.0))
    axes[1].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _short(name: str) -> str:
    """A hand's or object's name on a figure: a file's stem, a preset's name."""
    path = Path(name)
    return path.stem if path.suffix else name
