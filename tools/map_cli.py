"""`haptic map`: list the presets, check a map for a fingertip, build one from a mesh.

Heavy libraries (numpy, scipy, trimesh, matplotlib) are imported inside the handlers, so
building the CLI stays cheap.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from service.episode.scenario import RunSettings
from tools.arg_types import number, setting

DEFAULT_RADIUS = 0.008
DEFAULT_STEP = 0.01


def register(p: argparse.ArgumentParser) -> None:
    p.description = ("Height maps: the presets, a check of what a map offers a fingertip, and "
                     "maps built from meshes. Lengths in metres.")
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
    check.add_argument("--spacing", type=float, metavar="M",  # checked as `haptic run` does
                       help="metres between samples (map files only)")
    check.add_argument("--radius", type=setting(RunSettings, "radius"),
                       default=DEFAULT_RADIUS, metavar="M",
                       help="fingertip radius in metres (default: %(default)s)")
    check.add_argument("--step", type=setting(RunSettings, "step"),
                       default=DEFAULT_STEP, metavar="M",
                       help="step length in metres (default: %(default)s)")
    check.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    check.add_argument("--plot", type=Path, metavar="FILE.png",
                       help="draw the map, its plains and the pits the tip cannot reach")
    check.set_defaults(handler=run_check)

    mesh = jobs.add_parser(
        "from-mesh", help="a height map of a meshed object (STL, OBJ, PLY, GLB...) seen from "
                          "above",
        description="Cast one vertical ray per sample onto a mesh (trimesh) and write the "
                    "heights seen from above, in metres above the table the part rests on "
                    "(its lowest point). Rows of the map run along y.")
    mesh.add_argument("mesh", type=Path, metavar="MESH", help="a mesh file trimesh reads")
    mesh.add_argument("--spacing", type=setting(RunSettings, "spacing"), required=True,
                      metavar="M",
                      help="metres between samples, e.g. 0.0005")
    mesh.add_argument("-o", "--output", type=Path, required=True, metavar="FILE",
                      help="where to write the map: .npy (or .csv/.txt)")
    mesh.add_argument("--up", default="z", choices=("z", "-z", "y", "-y", "x", "-x"),
                      help="the mesh's axis that points up, away from the table; y turns the "
                           "mesh a quarter turn about x (map y = -mesh z), x a quarter turn "
                           "about y (map x = -mesh z) (default: %(default)s)")
    mesh.add_argument("--scale", type=number(1e-6, 1e6), default=1.0, metavar="FACTOR",
                      help="multiply the mesh's coordinates by this to get metres: 0.001 for "
                           "a mesh in millimetres (default: %(default)s)")
    mesh.add_argument("--region", metavar="XMIN,YMIN,XMAX,YMAX",
                      help="the part of the (turned, scaled) mesh to map, in metres; default: "
                           "its footprint and two samples of table round it")
    mesh.add_argument("--radius", type=setting(RunSettings, "radius"),
                      default=DEFAULT_RADIUS, metavar="M",
                      help="fingertip radius for the check of the new map "
                           "(default: %(default)s)")
    mesh.add_argument("--step", type=setting(RunSettings, "step"),
                      default=DEFAULT_STEP, metavar="M",
                      help="step length for the check (default: %(default)s)")
    mesh.set_defaults(handler=run_from_mesh)


def run_list(args: argparse.Namespace) -> int:
    from service.localization.presets import describe

    rows = describe()
    width = max(len(syntax) for syntax, _ in rows)
    for syntax, summary in rows:
        print(f"{syntax:<{width}}  {summary}")
    print("\nSIZE is the side in units of 10 mm (default 20: 200 mm); SEED draws a new surface "
          "of the family (default 0). Every preset is sampled at 1 mm, heights in metres.")
    return 0


def run_check(args: argparse.Namespace) -> int:
    from service.bounds import bound_of
    from service.episode.scenario import RunSettings
    from service.errors import ConfigError
    from service.localization.map_check import check_map
    from service.localization.maps import load_map
    from tools.outputs import check_outputs

    if not (args.step > 0):
        raise ConfigError(f"--step must be a positive number of metres, got {args.step}")
    # the spacing `haptic run` takes, with its words: a map check passed --spacing 1 with a
    # warning that the run then refused
    bound_of(RunSettings, "spacing").check("--spacing", args.spacing)
    check_outputs(args.json, figures=(args.plot,), inputs=(args.map,))
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


def run_from_mesh(args: argparse.Namespace) -> int:
    from service.localization.map_check import check_map
    from service.localization.mesh_map import (
        check_output,
        mesh_height_map,
        parse_region,
        save_heights,
    )

    check_output(args.output)  # before the ray casts, not after
    result = mesh_height_map(args.mesh, args.spacing, up=args.up, scale=args.scale,
                             region=parse_region(args.region))
    m = result.height_map
    x0, y0 = result.origin
    x_max, y_max = m.extent
    print(f"mesh {args.mesh}: {result.faces} triangles; map {m.shape[1]} x {m.shape[0]} "
          f"samples at {m.spacing * 1e3:g} mm covering x {x0:.4g}..{x0 + x_max:.4g} m, "
          f"y {y0:.4g}..{y0 + y_max:.4g} m of the mesh; the part fills "
          f"{result.hit_share:.0%} of it")
    for warning in result.warnings:
        print(f"warning: {warning}")
    save_heights(m, args.output)
    print(f"map written to {args.output}: map (0, 0) is the mesh's ({x0:.4g}, {y0:.4g}) m")
    print("\n".join(check_map(m, args.radius, args.step).lines()))
    print(f"use it: haptic run --map {args.output} --spacing {args.spacing:g}")
    return 0
