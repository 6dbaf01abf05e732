"""Command-line options shared by `haptic run`, `haptic emulate` and the bench scenarios."""

from __future__ import annotations

import argparse
import math
import textwrap
from typing import Any

from service.bounds import check_keywords, keyword_params, settable
from service.episode.scenario import RunSettings
from service.errors import ConfigError
from service.localization.models import HARDWARE_SENSOR_SIGMA
from service.registry import LOCALIZERS, POLICIES

SCALAR_TYPES = frozenset({"int", "float", "str", "bool", "None"})


def localizer_options(name: str) -> dict[str, Any]:
    """The keywords `--localizer-option` can set for localizer `name`, with their defaults:
    its constructor's (and, through `**options`, its base classes') scalar keywords."""
    return {option: default for option, (hint, default)
            in keyword_params(LOCALIZERS.load(name)).items() if settable(hint)}


def localizer_options_help() -> str:
    """Every localizer's options and defaults, for --help."""
    lines = ["--localizer-option NAME=VALUE sets (default in parentheses):"]
    for name in LOCALIZERS.names():
        opts = ", ".join(f"{k} ({'auto' if v is None else v})"
                         for k, v in localizer_options(name).items())
        lines += textwrap.wrap(f"{name}: {opts}", 78, initial_indent="  ",
                               subsequent_indent="    ")
    return "\n".join(lines)


def check_localizer_options(algorithm: str, options: dict[str, Any]) -> None:
    """ConfigError naming a mistyped option (with the closest valid name and the valid
    names) or a value out of its range."""
    check_keywords(LOCALIZERS.load(algorithm), options, f"--localizer-option: {algorithm}")


def add_scenario_options(parser: argparse.ArgumentParser, *, defaults: RunSettings,
                         localizer: bool = True, radius: bool = True,
                         algorithm_help: str | None = None, own_maps: bool = False) -> None:
    """Map, finger, algorithm, policy and noise options, with `defaults` shown in --help.

    `localizer=False` leaves out what only a localizer uses and `radius=False` the fingertip
    radius (for the servo-bus emulator, whose hand file sets it);
    `algorithm_help` replaces the default's wording when there is no single default;
    `own_maps` (a bench that builds its own surfaces) keeps --map and --spacing out of
    --help: the bench refuses them, naming the command that takes a map.
    """
    g = parser.add_argument_group("scenario")
    g.add_argument("--map", default=defaults.map, metavar="NAME|PATH",
                   help=argparse.SUPPRESS if own_maps else
                   "preset NAME[:SIZE[:SEED]] (peaks, bumps, eggcrate, plate, pattern, "
                   "shell, terrain; profile:KIND[:SIZE[:SEED]] for a 1-D profile; "
                   "`haptic map list` describes them) or a .npy/.csv/.txt grid of heights "
                   "in metres (default: %(default)s)")
    g.add_argument("--spacing", type=float, default=None, metavar="M",
                   help=argparse.SUPPRESS if own_maps else
                   "metres between samples, for map files")
    if radius:
        g.add_argument("--radius", type=float, default=defaults.radius, metavar="M",
                       help="fingertip radius in metres (default: %(default)s)")
    g.add_argument("--step", type=float, default=defaults.step, metavar="M",
                   help="step length in metres (default: %(default)s)")
    g.add_argument("--noise", action="store_true", default=defaults.noise,
                   help="always on here: BENCHMARKS.md B2's noise and model-mismatch models "
                        "are what this benchmark measures under" if defaults.noise else
                        "turn on BENCHMARKS.md B2's noise and model-mismatch models")
    if not localizer:
        return
    g.add_argument("--algorithm", default=defaults.algorithm, choices=LOCALIZERS.names(),
                   help=f"localizer ({algorithm_help or 'default: %(default)s'}). "
                        f"{LOCALIZERS.help()}")
    g.add_argument("--policy", default=defaults.policy, choices=POLICIES.names(),
                   help=f"exploration policy (default: %(default)s). {POLICIES.help()}")
    g.add_argument("--sensor-sigma", type=float, default=None, metavar="M",
                   help="measurement noise (metres) the localizer assumes; default: exact "
                        "for a noise-free simulation, B2's with --noise, "
                        f"{HARDWARE_SENSOR_SIGMA} m on hardware")
    g.add_argument("--max-steps", type=int, default=defaults.max_steps, metavar="N",
                   help="give up after N steps (default: %(default)s)")
    g.add_argument("--headings", type=int, default=defaults.headings, metavar="N",
                   help="headings in the pose table: a noise-free simulated start's and "
                        "elimination's candidates (default: %(default)s); a grid's own is "
                        "--localizer-option headings=N")
    g.add_argument("--sweep", choices=("paper", "full"), default=None,
                   help="elimination only: the paper's band test plus 5 exact tests per "
                        "step (paper, default), or the exact test on every candidate (full)")
    g.add_argument("--localizer-option", action="append", default=[], metavar="NAME=VALUE",
                   dest="localizer_option",
                   help="a keyword of the localizer, e.g. work=4000 for particles "
                        "(repeatable; numbers and true/false are converted; the names are "
                        "listed below)")
    parser.epilog = localizer_options_help()


def parse_start(text: str | None) -> tuple[float, float, float] | None:
    """'X,Y,HEADING_DEG' (metres, metres, degrees) to (x, y, heading in radians)."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        x, y, heading_deg = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"--start takes X,Y,HEADING_DEG (metres, metres, degrees), "
                          f"got '{text}'") from None
    if not all(math.isfinite(v) for v in (x, y, heading_deg)):
        raise ConfigError(f"--start values must be finite, got '{text}'")
    return (x, y, math.radians(heading_deg % 360.0))  # 60000 deg was echoed as 1047 rad


def parse_localizer_options(items: list[str]) -> dict[str, Any]:
    """['work=4000', 'drop=30.5'] to {'work': 4000, 'drop': 30.5}."""
    options: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name.isidentifier():
            raise ConfigError(f"--localizer-option takes NAME=VALUE, got '{item}'")
        options[name] = _literal(text)
    return options


def _literal(text: str) -> Any:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def settings_from_args(args: argparse.Namespace, **overrides: Any) -> RunSettings:
    options = parse_localizer_options(getattr(args, "localizer_option", None) or [])
    algorithm = overrides.get("algorithm", getattr(args, "algorithm", None))
    if algorithm is not None:
        check_localizer_options(algorithm, options)
    if getattr(args, "sweep", None):
        if algorithm != "elimination":
            raise ConfigError("--sweep applies only to --algorithm elimination")
        options["sweep"] = args.sweep
    _refuse_unread_headings(args, algorithm, noise=overrides.get("noise", args.noise))
    fields: dict[str, Any] = dict(
        map=args.map, spacing=args.spacing, step=args.step, noise=args.noise,
        localizer_options=options,
        sensor_sigma=getattr(args, "sensor_sigma", None),
        seed=getattr(args, "seed", 0), start=parse_start(getattr(args, "start", None)))
    for name in ("radius", "algorithm", "policy", "max_steps", "headings"):  # not in emulate
        if hasattr(args, name):
            fields[name] = getattr(args, name)
    fields.update(overrides)
    return RunSettings(**fields)


def _refuse_unread_headings(args: argparse.Namespace, algorithm: str | None, *,
                            noise: bool) -> None:
    """`--headings` shapes the pose table: a noise-free simulated start is drawn from it and
    elimination's candidates fill it. Anywhere else nothing reads it, and a held-out check's
    `--noise --headings 72` went without a word: refused, saying where it applies."""
    headings = getattr(args, "headings", None)
    if headings is None or headings == RunSettings().headings or algorithm == "elimination":
        return
    drawn_from_table = (not noise and getattr(args, "start", None) is None
                        and getattr(args, "backend", "sim") == "sim")
    if not drawn_from_table:
        raise ConfigError("--headings shapes the pose table, which only a noise-free simulated "
                          "start without --start and --algorithm elimination read; here "
                          "nothing would: leave it out (a grid's own headings are "
                          "--localizer-option headings=N)")
