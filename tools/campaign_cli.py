"""`haptic campaign FILE.toml`: run a grid of scenarios on an executor, resumably.

One progress bar covers every episode; each finished episode is stored at once, so Ctrl-C
(or a kill) loses only the episodes still running, and running the same command again
finishes the rest. Reports are rebuilt from the store at the end, or on Ctrl-C.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from tools.executor import add_executor_options


def register(p: argparse.ArgumentParser) -> None:
    from tools.campaign import __doc__ as format_doc

    p.description = ("Run a grid of benchmark scenarios from a TOML file: one CSV row per "
                     "episode (episodes.csv), a figure per scenario (figures/), a Markdown "
                     "summary (summary.md). Interrupted, it resumes where it stopped.\n\n"
                     "The file:\n" + format_doc.split("\n\n")[1] + "\n")
    p.add_argument("campaign", type=Path, metavar="FILE.toml", help="the campaign to run")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="where results go (default: the file's `out`, or FILE-results "
                        "beside it)")
    p.add_argument("--fresh", action="store_true",
                   help="forget finished episodes and run everything again")
    add_executor_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from service.episode.scenario import check_scenario
    from service.errors import ConfigError
    from service.localization.map_check import check_map
    from service.localization.maps import load_map
    from tools.bench_common import progress
    from tools.campaign import Store, load_campaign, map_digest
    from tools.executor import Failed, make_executor

    campaign = load_campaign(args.campaign, args.out)
    if campaign.out.exists() and not campaign.out.is_dir():
        raise ConfigError(f"--out {campaign.out} is a file, not a folder")
    maps = {}  # loaded first: a map that fails leaves no results folder behind
    digests = {}
    for sc in campaign.scenarios:
        key = sc.settings.map
        if key not in maps:
            maps[key] = load_map(key, sc.settings.spacing)
            digests[key] = map_digest(key)
            for warning in check_map(maps[key], sc.settings.radius, sc.settings.step).warnings:
                print(f"warning: {key}: {warning}")
        try:  # what `haptic run` refuses is refused here, before any episode
            check_scenario(sc.settings, maps[key])
        except ConfigError as exc:
            raise ConfigError(f"campaign {args.campaign}: scenario {sc.name}: {exc}") from None
    # reached before anything is written or forgotten: a cluster that is not there changes
    # nothing (`--fresh` deleted the finished episodes first)
    executor = make_executor(args.workers, args.scheduler)
    try:
        campaign.out.mkdir(parents=True, exist_ok=True)
        (campaign.out / "campaign.toml").write_text(campaign.source)
    except OSError as exc:
        executor.close()
        raise ConfigError(f"cannot write results to {campaign.out}: {exc.strerror or exc}; "
                          "choose another `out` (or --out)") from None
    store = Store(campaign.out)
    if args.fresh and store.path.exists():
        store.path.unlink()
    current = {sc.key: digests[sc.settings.map] for sc in campaign.scenarios}
    done = store.load()
    changed = [k for k, r in done.items() if k[0] in current and _stale(r, current)]
    if changed:  # run on another version of its map file: not this campaign's result
        print(f"{len(changed)} finished episodes ran on another version of their map file: "
              "they run again")
    # an episode that raised is run again too: what made it raise may be mended
    done = {k: r for k, r in done.items() if not _stale(r, current) and r.get("error") is None}
    todo = [(sc, seed) for sc in campaign.scenarios for seed in campaign.seeds
            if (sc.key, seed) not in done]
    print(f"campaign {campaign.name}: {len(campaign.scenarios)} scenarios x {campaign.runs} "
          f"runs = {campaign.episodes} episodes; {campaign.episodes - len(todo)} already "
          f"done, {len(todo)} to run on {executor.describe()}; results in {campaign.out}")
    settings = [dataclasses.replace(sc.settings, seed=seed) for sc, seed in todo]
    finished = False
    if not settings:  # all done before: no bar (it printed "18/18, ? left" twice)
        with executor:
            _report(campaign, store, current, complete=True)
        return 0
    with executor, progress(campaign.episodes, campaign.name, unit="episode",
                            initial=campaign.episodes - len(todo)) as bar:
        try:
            for index, outcome in executor.run(settings, maps):
                scenario, seed = todo[index]
                failed = isinstance(outcome, Failed)
                store.append({"scenario": scenario.key, "name": scenario.name, "seed": seed,
                              "map_sha256": digests[scenario.settings.map],
                              "episode": None if failed else outcome.to_json(),
                              "error": outcome.error if failed else None,
                              "refused": failed and outcome.refused,
                              "executor": executor.describe(), "workers": executor.workers})
                bar.update()
            finished = True
        finally:
            bar.close()
            records = _report(campaign, store, current, complete=finished)
    return _status(records)


def _stale(record: dict, current: dict[str, str | None]) -> bool:
    """Whether `record` ran on another version of its scenario's map file than the one
    there now (records from before digests were kept are taken as they are): a resumed
    campaign presented a changed file's new scenario with the old file's results."""
    ran = record.get("map_sha256")
    return ran is not None and ran != current.get(record["scenario"])


def _status(records: dict) -> int:
    """0, or the episodes that raised, in one line: refused settings are the user's to
    mend (exit 2), anything else a fault (exit 1). A campaign with every episode of two
    scenarios refused exited 0."""
    from service.errors import ConfigError, ServiceError

    failed = [r for r in records.values() if r.get("error") is not None]
    if not failed:
        return 0
    refused = [r for r in failed if r.get("refused")]
    first = (refused or failed)[0]
    message = (f"{len(failed)} episodes raised, e.g. scenario {first['name']} seed "
               f"{first['seed']}: {first['error']}; mend it and run the same command again "
               "(they run again)")
    raise (ConfigError if refused else ServiceError)(message)


def _report(campaign, store, current: dict[str, str | None], complete: bool) -> dict:
    """The reports from the finished episodes of this campaign's maps as they are now;
    returns those records."""
    from tools.campaign_report import rows_of, write_csv, write_figures, write_summary

    records = {k: r for k, r in store.load().items() if not _stale(r, current)}
    grouped = rows_of(campaign, records)
    executors = sorted({r.get("executor", "?") for r in records.values()})
    write_csv(campaign.out / "episodes.csv", campaign, grouped)
    write_summary(campaign.out / "summary.md", campaign, grouped, executors, complete)
    figures = write_figures(campaign.out / "figures", grouped)
    done = sum(len(rows) for _, rows in grouped)
    state = "done" if complete else "interrupted: run the same command again to finish"
    print(f"{done} of {campaign.episodes} episodes finished ({state}); "
          f"{campaign.out / 'episodes.csv'}, {campaign.out / 'summary.md'}, "
          f"{len(figures)} figures in {campaign.out / 'figures'}")
    if complete:
        print((campaign.out / "summary.md").read_text())
    return records
