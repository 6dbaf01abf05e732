"""A campaign's results: one CSV row per episode, a Markdown summary, a figure per scenario.

Everything here is rebuilt from the episode store, so an interrupted campaign's reports
show what finished, and a resumed one's show everything.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

import numpy as np

from tools.bench_common import fmt, percentile
from tools.campaign import Campaign, Scenario

EPISODE_COLUMNS = ("scenario", "seed", "outcome", "success", "wrong_declaration", "converged",
                   "steps", "position_error_mm", "heading_error_deg", "compute_first_ms",
                   "compute_after_first_median_ms", "compute_after_first_p99_ms",
                   "policy_median_ms", "workers", "error")


def episode_row(scenario: Scenario, record: dict[str, Any]) -> dict[str, Any]:
    """The CSV row of one stored episode: the grid's choices, the outcome, timings."""
    row: dict[str, Any] = {"scenario": scenario.name, **scenario.choices,
                           "seed": record["seed"], "workers": record.get("workers"),
                           "error": record.get("error") or ""}
    episode = record.get("episode")
    if episode is None:
        return {**row, "outcome": "error"}
    steps = episode["steps"]
    later = [s["compute_ms"] for s in steps[1:]]
    wrong, success = episode["wrong_declaration"], episode["success"]
    heading = episode["heading_error"]
    return {**row,
            "outcome": "WRONG" if wrong else "localized" if success else "not yet",
            "success": success, "wrong_declaration": wrong, "converged": episode["converged"],
            "steps": len(steps),
            "position_error_mm": (None if episode["position_error"] is None
                                  else episode["position_error"] * 1e3),
            "heading_error_deg": None if heading is None else float(np.degrees(heading)),
            "compute_first_ms": steps[0]["compute_ms"] if steps else None,
            "compute_after_first_median_ms": percentile(later, 50),
            "compute_after_first_p99_ms": percentile(later, 99),
            "policy_median_ms": percentile((s["policy_ms"] for s in steps), 50)}


def rows_of(campaign: Campaign, records: dict[tuple[str, int], dict[str, Any]]
            ) -> list[tuple[Scenario, list[dict[str, Any]]]]:
    """Each scenario with the rows of its finished episodes, in seed order."""
    return [(sc, [episode_row(sc, records[(sc.key, seed)]) for seed in campaign.seeds
                  if (sc.key, seed) in records]) for sc in campaign.scenarios]


def write_csv(path: Path, campaign: Campaign, grouped) -> None:
    grid_keys = list(dict.fromkeys(k for sc in campaign.scenarios for k in sc.choices))
    columns = ["scenario", *grid_keys, *EPISODE_COLUMNS[1:]]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for _, rows in grouped:
            writer.writerows(rows)


def scenario_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    done = [r for r in rows if r["outcome"] != "error"]
    count = {o: sum(r["outcome"] == o for r in rows)
             for o in ("localized", "not yet", "WRONG", "error")}
    return {"episodes": len(rows), **count,
            "steps_median": percentile((r["steps"] for r in done), 50),
            "steps_p90": percentile((r["steps"] for r in done), 90),
            "position_error_mm_median": percentile(
                (r["position_error_mm"] for r in done if r["success"]), 50),
            "compute_first_ms_median": percentile(
                (r["compute_first_ms"] for r in done if r["compute_first_ms"] is not None), 50),
            "compute_after_first_p99_ms_worst": max(
                (r["compute_after_first_p99_ms"] for r in done
                 if r["compute_after_first_p99_ms"] is not None), default=None)}


def write_summary(path: Path, campaign: Campaign, grouped, executors: list[str],
                  complete: bool) -> None:
    lines = [f"# Campaign: {campaign.name}", "",
             f"{len(campaign.scenarios)} scenarios x {campaign.runs} runs (seeds "
             f"{campaign.seeds.start}-{campaign.seeds.stop - 1}); "
             f"{sum(len(rows) for _, rows in grouped)} of {campaign.episodes} episodes "
             f"finished{'' if complete else ' (interrupted: run the campaign again to finish)'}.",
             "",
             "Episodes ran on: " + "; ".join(executors) + ". Compute per step is timed inside "
             "each episode; workers sharing a machine share its cores, so compare timings "
             "only between runs with the same workers.", "",
             "| scenario | episodes | localized | not yet | **WRONG** | errors | steps median "
             "/ p90 | position error median (mm) | first step ms | worst p99 after it, ms |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for sc, rows in grouped:
        s = scenario_summary(rows)
        wrong = f"**{s['WRONG']}**" if s["WRONG"] else "0"
        lines.append(f"| {sc.name} | {s['episodes']} | {s['localized']} | {s['not yet']} | "
                     f"{wrong} | {s['error']} | {fmt(s['steps_median'], 'g')} / "
                     f"{fmt(s['steps_p90'], 'g')} | "
                     f"{fmt(s['position_error_mm_median'], '.3f')} | "
                     f"{fmt(s['compute_first_ms_median'])} | "
                     f"{fmt(s['compute_after_first_p99_ms_worst'])} |")
    path.write_text("\n".join(lines) + "\n")


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.-]+", "_", text).strip("_")[:80] or "scenario"


def write_figures(folder: Path, grouped) -> list[Path]:
    """Per scenario: outcomes and steps of each episode, and compute per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tools.plots import plain_log_ticks

    folder.mkdir(exist_ok=True)
    paths = []
    colours = {"localized": "tab:green", "not yet": "0.6", "WRONG": "red", "error": "k"}
    for i, (sc, rows) in enumerate(grouped):
        if not rows:
            continue
        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.4))
        for outcome, colour in colours.items():
            mine = [r for r in rows if r["outcome"] == outcome]
            if not mine:  # an empty category's legend entry came out in default blue
                continue
            label = f"{outcome} ({len(mine)})"
            if outcome == "error":  # no steps to draw: a mark at its seed
                a.plot([r["seed"] for r in mine], [0] * len(mine), "kx", ms=8, mew=2,
                       label=label, clip_on=False)
            else:
                a.bar([r["seed"] for r in mine], [r.get("steps") or 0 for r in mine],
                      color=colour, label=label)
        a.set(xlabel="seed", ylabel="steps", title="steps per episode, by outcome")
        a.xaxis.get_major_locator().set_params(integer=True)  # seeds are whole numbers
        # below the axes, not over the first bars
        a.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4)
        done = [r for r in rows if r["outcome"] != "error"]
        a_first = [r["compute_first_ms"] for r in done]
        med = [r["compute_after_first_median_ms"] for r in done]
        p99 = [r["compute_after_first_p99_ms"] for r in done]
        seeds = [r["seed"] for r in done]
        b.plot(seeds, a_first, "k_", ms=8, label="first step")
        b.plot(seeds, med, "o", color="tab:purple", ms=3, label="median after it")
        b.plot(seeds, p99, "^", color="tab:purple", ms=4, alpha=0.5, label="p99 after it")
        b.set(xlabel="seed", ylabel="ms per update", yscale="log",
              title="localizer compute per episode")
        plain_log_ticks(b.yaxis)  # 3x10^0, 4x10^0 ... crowded the axis
        b.xaxis.get_major_locator().set_params(integer=True)
        b.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
        fig.suptitle(sc.name, fontsize=10)
        fig.tight_layout()
        path = folder / f"{i:02d}-{slug(sc.name)}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    for old in folder.glob("[0-9][0-9]-*.png"):  # a changed campaign's figures are gone
        if old not in paths:
            old.unlink()
    return paths
