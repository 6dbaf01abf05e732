"""`haptic map`: list the presets, check a map for a fingertip, build one from a mesh.

Heavy libraries (numpy, scipy, trimesh, matplotlib) are imported inside the handlers, so
building the CLI stays cheap.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DEFAULT_RADIUS = 0.008
DEFAULT_STEP = 0.01


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="list, check or build height maps",
                       description="Height maps: the presets, a check of what a map offers a "
                                   "fingertip, and maps built from meshes. Lengths in metres.")
    jobs = p.add_subparsers(dest="map_command", metavar="JOB", required=True)

    ls = jobs.add_parser("list", help="describe every preset",
                         description="Every built-in map preset with its syntax.")
    ls.set_defaults(handler=run_list)

    check = jobs.add_parser(
        "check", help="what a map offers a fingertip: relief, slopes, features, plains, "
                      "symmetries, and warnings",
        description="Check a preset or a map file for a fingertip: height range, steepest "
                    "slope, smallest feature against the tip, hidden pits, share of plains, "
                    "symmetries; warns about heights that look like millimetres. Exits 2 when "
                    "the tip cannot be used on the map.")
    check.add_argument("map", metavar="FILE|PRESET",
                       help="a preset (see `haptic map list`) or a .npy/.csv/.txt grid of "
                            "heights in metres, rows along y")
    check.add_argument("--spacing", type=float, metavar="M",
                       help="metres between samples (map files only)")
    check.add_argument("--radius", type=float, default=DEFAULT_RADIUS, metavar="M",
                       help="fingertip radius in metres (default: %(default)s)")
    check.add_argument("--step", type=float, default=DEFAULT_STEP, metavar="M",
                       help="step length in metres (default: %(default)s)")
    check.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    check.add_argument("--plot", type=Path, metavar="FILE.png",
                       help="draw the map, its plains and the pits the tip cannot reach")
    check.set_defaults(handler=run_check)


def run_list(args: argparse.Namespace) -> int:
    from service.localization.presets import describe

    rows = describe()
    width = max(len(syntax) for syntax, _ in rows)
    for syntax, summary in rows:
        print(f"{syntax:<{width}}  {summary}")
    print("\nSIZE is the side in units of 10 mm (default 20: 200 mm); SEED draws a new surface "
          "of the family (default 0). Every preset is sampled at 1 mm, heights in metres.")
    return 0


def _check_outputs(*paths: Path | None) -> None:
    from service.errors import ConfigError

    for path in paths:
        if path is not None and not path.resolve().parent.is_dir():
            raise ConfigError(f"cannot write {path}: folder {path.parent} does not exist")


def run_check(args: argparse.Namespace) -> int:
    from service.errors import ConfigError
    from service.localization.map_check import check_map
    from service.localization.maps import load_map

    if not (args.step > 0):
        raise ConfigError(f"--step must be a positive number of metres, got {args.step}")
    _check_outputs(args.json, args.plot)
    height_map = load_map(args.map, args.spacing)
    report = check_map(height_map, args.radius, args.step)
    print("\n".join(report.lines()))
    if args.json:
        args.json.write_text(json.dumps(report.to_json(), indent=1))
        print(f"report written to {args.json}")
    if args.plot:
        from tools.map_plots import check_figure

        check_figure(height_map, report, args.plot)
        print(f"figure written to {args.plot}")
    return 0
