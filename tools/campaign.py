"""`haptic campaign FILE.toml`: a grid of scenarios, each episode run once, resumable.

    name = "noise sweep"       # optional
    runs = 20                  # seeded episodes per scenario (seeds first_seed, ...)
    first_seed = 0             # optional
    out = "sweep-results"      # optional, beside FILE; default: FILE's stem + "-results"
    [fixed]                    # settings every scenario shares
    noise = true
    max_steps = 60
    [grid]                     # every combination of these lists is one scenario
    algorithm = ["particles", "elimination"]
    map = ["bumps:20:1", "plate:20:0"]

Settings are `haptic run`'s (`RunSettings` fields but the seed and start), with their
types and ranges checked on load. Every finished episode is appended at once to
`OUT/episodes.jsonl`, keyed by its scenario's settings and its seed, so a campaign that is
interrupted (Ctrl-C, a kill, a crash) resumes where it stopped when run again: finished
episodes are not run twice, and changing the grid reruns only what is new.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import itertools
import json
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.episode.scenario import RunSettings
from service.errors import ConfigError
from service.localization.maps import MAP_FILE_SUFFIXES

SETTINGS = [f.name for f in dataclasses.fields(RunSettings) if f.name not in ("seed", "start")]
TOP_KEYS = ("name", "runs", "first_seed", "out", "fixed", "grid")
MAX_EPISODES = 1_000_000


@dataclass(frozen=True)
class Scenario:
    name: str
    """The grid's choices, e.g. "algorithm=particles, map=plate:20:0"."""
    settings: RunSettings
    choices: dict[str, Any]
    home: Path | None = None
    """The campaign file's folder: a map file is keyed by its path from there, so a
    campaign folder moved or copied elsewhere resumes (keyed by the absolute path, it
    started over)."""

    @property
    def key(self) -> str:
        """Names the scenario's settings (all but the seed) in the episode store."""
        data, map_file = self._settings()
        if self.home is not None and map_file:
            data["map"] = Path(os.path.relpath(Path(data["map"]).resolve(),
                                               self.home.resolve())).as_posix()
        return hashlib.sha1(json.dumps(data, sort_keys=True).encode()).hexdigest()[:12]

    @property
    def identity(self) -> str:
        """The settings with a map file named by the file itself (device and inode): one
        file by two names, a hard link too, is one scenario."""
        data, map_file = self._settings()
        if map_file:
            try:
                found = os.stat(data["map"])
                data["map"] = [found.st_dev, found.st_ino]
            except OSError:  # missing: refused when it is loaded, in its own words
                pass
        return json.dumps(data, sort_keys=True)

    def _settings(self) -> tuple[dict[str, Any], bool]:
        """The settings but the seed, as JSON data, and whether the map is a file."""
        data = dataclasses.replace(self.settings, seed=0).to_json()
        return data, Path(data["map"]).suffix.lower() in MAP_FILE_SUFFIXES


@dataclass(frozen=True)
class Campaign:
    name: str
    runs: int
    first_seed: int
    out: Path
    scenarios: list[Scenario]
    source: str
    """The TOML text, kept beside the results."""

    @property
    def seeds(self) -> range:
        return range(self.first_seed, self.first_seed + self.runs)

    @property
    def episodes(self) -> int:
        return self.runs * len(self.scenarios)


def _fail(path: Path, message: str) -> ConfigError:
    return ConfigError(f"campaign {path}: {message}")


def _unknown(path: Path, where: str, key: str, known: list[str]) -> ConfigError:
    close = difflib.get_close_matches(key, known, n=1)
    hint = f"did you mean '{close[0]}'? " if close else ""
    return _fail(path, f"unknown key '{key}' in {where}; {hint}it takes {', '.join(known)}")


def load_campaign(path: Path, out: Path | None = None) -> Campaign:
    """Read and check a campaign file; every scenario's settings are built (and so checked)."""
    try:
        source = path.read_text()
        data = tomllib.loads(source)
    except FileNotFoundError:
        raise ConfigError(f"campaign file '{path}' does not exist") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise _fail(path, f"not valid TOML: {exc}") from None
    for key in data:
        if key not in TOP_KEYS:
            raise _unknown(path, "the top level", key, list(TOP_KEYS))
    name = data.get("name", path.stem)
    runs, first_seed = data.get("runs"), data.get("first_seed", 0)
    for label, value, lo in (("runs", runs, 1), ("first_seed", first_seed, 0)):
        if not isinstance(value, int) or isinstance(value, bool) or value < lo:
            raise _fail(path, f"{label} must be a whole number >= {lo}, got {value!r}")
    if not isinstance(name, str):
        raise _fail(path, f"name must be a string, got {name!r}")
    fixed, grid = data.get("fixed", {}), data.get("grid", {})
    for where, table in (("[fixed]", fixed), ("[grid]", grid)):
        if not isinstance(table, dict):
            raise _fail(path, f"{where} must be a table of settings")
        for key in table:
            if key not in SETTINGS:
                raise _unknown(path, where, key, SETTINGS)
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise _fail(path, f"[grid] {key} must be a non-empty list, e.g. {key} = "
                              f"[{json.dumps(fixed.get(key, 'A'))}, ...]")
        if key in fixed:
            raise _fail(path, f"'{key}' is in both [fixed] and [grid]")
    fixed = _beside(path, fixed)
    grid = {k: [_beside(path, {k: v})[k] for v in values] for k, values in grid.items()}
    scenarios = []
    for combo in itertools.product(*grid.values()):
        choices = dict(zip(grid, combo, strict=True))
        label = ", ".join(f"{k}={_text(v)}" for k, v in choices.items()) or "fixed"
        try:
            settings = RunSettings(**fixed, **choices)
        except ConfigError as exc:
            raise _fail(path, f"scenario {label}: {exc}") from None
        scenarios.append(Scenario(label, settings, choices, path.parent))
    seen: dict[str, str] = {}
    for sc in scenarios:  # "a.npy" and "./a.npy" are one map: its episodes ran twice
        if sc.identity in seen:
            raise _fail(path, f"scenarios {seen[sc.identity]} and {sc.name} are the same "
                              "settings (a value listed twice, or one map file by two "
                              "names): list each once")
        seen[sc.identity] = sc.name
    if len(scenarios) * runs > MAX_EPISODES:
        raise _fail(path, f"{len(scenarios)} scenarios x {runs} runs is over "
                          f"{MAX_EPISODES:,} episodes")
    if out is None:
        given = data.get("out", f"{path.stem}-results")
        if not isinstance(given, str) or not given:
            raise _fail(path, f"out must be a folder name, got {given!r}")
        out = path.parent / given  # relative to the campaign file
    return Campaign(name, runs, first_seed, out, scenarios, source)


def map_digest(spec: str) -> str | None:
    """A map file's content digest (the first 16 hex digits of its SHA-256), None for a
    preset: a finished episode keeps the digest of the file it ran on."""
    if Path(spec).suffix.lower() not in MAP_FILE_SUFFIXES:
        return None
    digest = hashlib.sha256()
    with open(spec, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def _beside(path: Path, table: dict[str, Any]) -> dict[str, Any]:
    """`table` with a relative map file taken from the campaign file's folder, as `out`
    is: the same file runs alike from any working folder."""
    spec = table.get("map")
    if not (isinstance(spec, str) and Path(spec).suffix.lower() in MAP_FILE_SUFFIXES
            and not Path(spec).is_absolute()):
        return table
    return {**table, "map": str(path.parent / spec)}


def _text(value: Any) -> str:
    return json.dumps(value, sort_keys=True) if isinstance(value, (dict, list)) else str(value)


class Store:
    """Finished episodes, one JSON object per line, appended as each one arrives."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "episodes.jsonl"

    def load(self) -> dict[tuple[str, int], dict[str, Any]]:
        """Every complete record by (scenario key, seed). A line cut short by a kill is
        dropped from the file, so the next append starts on a clean line."""
        if not self.path.exists():
            return {}
        raw = self.path.read_bytes()
        good = raw[: raw.rfind(b"\n") + 1]
        if len(good) != len(raw):
            with self.path.open("r+b") as f:
                f.truncate(len(good))
        records = {}
        for line in good.splitlines():
            try:
                record = json.loads(line)
                records[(record["scenario"], int(record["seed"]))] = record
            except (ValueError, KeyError, TypeError):
                raise ConfigError(f"{self.path} has a line that is not an episode record; "
                                  "move the file away to start over") from None
        return records

    def append(self, record: dict[str, Any]) -> None:
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
