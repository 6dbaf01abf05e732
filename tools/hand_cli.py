"""`haptic run --object`: a hand holds an object and localizes it (issue 10), narrated.

The options join `haptic run`'s; `--object` switches the run from a finger on a map to a
hand holding an object (`--hand` then names the hand, default `two-finger`).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from service.errors import ConfigError
from service.localization.objects.files import OBJECT_FILE_SUFFIXES
from tools.arg_types import number
from tools.outputs import check_outputs, write_episode
from tools.signals import closed_whole
from tools.words import (
    NO_SAFE_MOVE,
    belief_text,
    fault_result,
    hand_step_text,
    interrupted_result,
    pose_text,
    steps_text,
    why_not_converged,
)

DEFAULT_HAND = "two-finger"


def add_object_options(parser: argparse.ArgumentParser) -> None:
    from service.episode.hand_scenario import HandSettings

    d = HandSettings()
    g = parser.add_argument_group(
        "a hand holding an object (with --object; --hand names the hand, default "
        f"{DEFAULT_HAND}; --seed, --noise, --max-steps, --algorithm, --plot and --json apply)")
    add_object_world_options(g)
    g.add_argument("--roll", type=number(1e-4, 0.02, "m"), default=d.step, metavar="M",
                   help="how far a finger rolls per step, metres (default: %(default)s)")
    g.add_argument("--threshold", type=number(0.0, 1000.0, "N"), default=d.threshold_n,
                   metavar="N",
                   help="grasp quality every move must keep (default: %(default)s)")
    g.add_argument("--no-gate", action="store_true",
                   help="the ablation: explore without the grasp-quality gate")
    g.add_argument("--single-finger", action="store_true",
                   help="only the hand's first finger, the object clamped in place")


def add_object_world_options(g: argparse._ActionsContainer) -> None:
    """The object and its physics: what `haptic run --object` and `haptic emulate --object`
    share, so that the same options (and seed) hold the same object the same way."""
    from service.episode.hand_scenario import HandSettings

    d = HandSettings()
    g.add_argument("--object", metavar="NAME|FILE",
                   help="an object preset (ellipse, rounded, blob, keyed; NAME:SEED picks a "
                        "member) or a file: a .csv outline (x,z metres, first row repeated "
                        "last) or a .stl/.obj/.ply mesh cut by --plane")
    g.add_argument("--plane", metavar="AXIS=V|PX,PY,PZ,NX,NY,NZ",
                   help="where a mesh is cut: x=V, y=V, z=V (metres) or a point and a normal; "
                        "default: z through the mesh's centroid")
    g.add_argument("--object-units", choices=("m", "mm"), default="m",
                   help="units of an object file (default: %(default)s)")
    g.add_argument("--mu", type=number(1e-3, 10.0), default=d.mu, help="friction coefficient "
                   "(default: %(default)s)")
    g.add_argument("--mass", type=number(0.0, 100.0, "kg"), default=d.mass_kg, metavar="KG",
                   help="the object's mass (default: %(default)s)")
    g.add_argument("--margin", type=number(0.0, 1000.0, "N"), default=d.margin_n, metavar="N",
                   help="disturbance the grasp must resist beyond the weight; below it the "
                        "object drops (default: %(default)s)")
    g.add_argument("--start-quality", type=number(0.0, 1000.0, "N"), default=d.start_n,
                   metavar="N",
                   help="grasp quality the hand starts with at least; the policy relies on "
                        "it (default: the threshold)")


def object_options_given(args: argparse.Namespace) -> list[str]:
    """The options of a hand holding an object that `args` sets away from their defaults,
    as flags: without --object they would be ignored (a held-out check's `--mu 0.9` and
    `--no-gate` on a map ran as if not given)."""
    from service.episode.hand_scenario import HandSettings

    d = HandSettings()
    defaults = {"roll": d.step, "threshold": d.threshold_n, "no_gate": False,
                "single_finger": False, "plane": None, "object_units": "m", "mu": d.mu,
                "mass": d.mass_kg, "margin": d.margin_n, "start_quality": d.start_n}
    return ["--" + name.replace("_", "-") for name, default in defaults.items()
            if hasattr(args, name) and getattr(args, name) != default]


def hand_settings(args: argparse.Namespace, **overrides):
    from service.episode.hand_scenario import HandSettings

    if args.object is None:
        raise ConfigError("--object is needed for a hand run")
    d = HandSettings()
    fields = dict(object=args.object, plane=args.plane, units=args.object_units,
                  hand=args.hand or DEFAULT_HAND, seed=getattr(args, "seed", 0),
                  noise=args.noise, mu=args.mu, mass_kg=args.mass, margin_n=args.margin,
                  start_n=args.start_quality,
                  # what only an episode uses (`haptic emulate` has none of it)
                  algorithm=getattr(args, "algorithm", d.algorithm),
                  step=getattr(args, "roll", d.step),
                  max_steps=getattr(args, "max_steps", d.max_steps),
                  threshold_n=getattr(args, "threshold", d.threshold_n),
                  gate=not getattr(args, "no_gate", False),
                  single_finger=getattr(args, "single_finger", False),
                  sensor_sigma=getattr(args, "sensor_sigma", None))
    fields.update(overrides)
    return HandSettings(**fields)


FINGER_ONLY = ("map", "spacing", "radius", "step", "policy", "headings", "sweep",
               "localizer_option")
"""`haptic run`'s options for a finger on a map (as attributes), which a hand ignores."""


def _refuse_finger_options(args: argparse.Namespace) -> None:
    """A finger's option given with --object (at other than its default: argparse keeps no
    record of what was typed) would be ignored without a word: refused, naming the hand's
    own where there is one."""
    from service.episode.scenario import RunSettings

    defaults = RunSettings()
    given = ["--" + name.replace("_", "-") for name in FINGER_ONLY if hasattr(args, name)
             and getattr(args, name) not in (None, [], getattr(defaults, name, None))]
    if given:
        instead = {"--step": "a hand's roll per step is --roll",
                   "--radius": "a hand's fingertip radii are in its hand file",
                   "--policy": "a hand always explores with the grasp-gated policy"}
        notes = [instead[flag] for flag in given if flag in instead]
        raise ConfigError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to a "
                          "finger on a map, not to a hand holding --object"
                          + (f" ({'; '.join(notes)})" if notes else ""))


def run_hand(args: argparse.Namespace, budget: dict[str, float] | None = None) -> int:
    """The body of `haptic run --object ...`."""
    from service.episode.hand_episode import simulate_hand
    from service.episode.hand_scenario import hand_for_backend, load_parts
    from service.localization.objects.symmetry import symmetry_warning

    if args.start is not None:
        raise ConfigError("--start places a finger on a map; an object's start is drawn "
                          "from --seed")
    _refuse_finger_options(args)
    settings = hand_settings(args)
    # before any work (a held-out check's --json in a missing folder failed after the run)
    check_outputs(args.json, figures=(args.plot,), inputs=(args.object, args.hand))
    parts = load_parts(settings)
    backend_factory = None
    if args.backend != "sim":
        backend_factory = _servo_hand(args, settings, budget or {})
        settings = hand_for_backend(settings, args.backend)
    fingers = len(parts.hand.fingers)
    print(f"object {parts.contour.name}: {parts.contour.extent * 1e3:.0f} mm across; hand "
          f"{parts.hand.name}: {fingers} finger{'s' if fingers > 1 else ''}; roll "
          f"{settings.step * 1e3:g} mm; {settings.algorithm}"
          f"{' with noise' if settings.noise else ''}"
          f"{'' if settings.gate else '; NO grasp gate (ablation)'}")
    if Path(settings.object).suffix.lower() in OBJECT_FILE_SUFFIXES:  # poses: its centroid's
        at = ", ".join(f"{v * 1e3:.2f}" for v in parts.contour.origin)
        along = ("its x axis" if len(parts.contour.axis) == 2 else "the plane's axis ("
                 + ", ".join(f"{v:.3f}" for v in parts.contour.axis) + ")")
        print(f"          poses are of its centroid, at ({at}) mm in the file's frame, "
              f"headings from {along}")
        if parts.contour.holes:  # a held-out ring's hole went without a word
            print(f"          the section's {parts.contour.holes} inner loop(s) are left out: "
                  "holes the fingers never reach; the object is its outer outline, the "
                  "centroid that outline's")
    if (warning := symmetry_warning(parts.field)) is not None:
        print(f"warning: {warning}")
    report = simulate_hand(settings, parts, on_step=None if args.quiet else _print_step,
                           snapshot_steps=(0,) if args.plot else (),
                           backend_factory=backend_factory, keep_on_interrupt=True)
    _print_summary(report, on_servos=backend_factory is not None)
    return write_episode(report, args.json, args.plot, _draw, failed=report.result.dropped
                         or (report.truth_known and report.score.wrong_declaration))


def _draw(report, path: Path) -> None:
    from tools.hand_plots import hand_figure

    hand_figure(report, path)


def _servo_hand(args: argparse.Namespace, settings, budget: dict[str, float]):
    """A factory of the hand on servos `--port` names (no I/O until the episode opens it);
    `budget`: the bus's `cycle_budget_s`, if `--cycle-budget` gave one."""
    from firmware_if.dxl_bus import check_port_exists
    from firmware_if.dynamixel_hand import DynamixelHand

    if args.backend != "dynamixel":
        raise ConfigError(f"--object runs on --backend sim or dynamixel, not {args.backend}")
    if not args.port:
        raise ConfigError("--backend dynamixel needs --port (the servo bus, e.g. what "
                          "`haptic emulate --hand HAND --object NAME` prints)")
    if settings.single_finger:
        raise ConfigError("--single-finger runs on the simulated hand only")
    check_port_exists(args.port)
    return lambda: closed_whole(DynamixelHand.from_cli(port=args.port, hand=settings.hand,
                                                       **budget))


def _print_step(step) -> None:
    from service.episode.hand_step import step_json

    print(hand_step_text(step_json(step)), flush=True)


def _pose_text(pose) -> str:
    return pose_text(pose, second="z")


def _print_summary(report, on_servos: bool = False) -> None:
    est = report.result.estimate
    if not report.truth_known:
        print(f"truth     unknown: the hand turned the object from the seed's start "
              f"({_pose_text(report.truth)}) and servos cannot see where it went")
    else:
        print(f"truth     {_pose_text(report.truth)}"
              + ("  (the seed's start: where `haptic emulate` placed the object if it "
                 "was given the same --hand, --object and --seed)" if on_servos else ""))
    if est is None or est.pose is None:
        print("estimate  none")
    else:
        # the spread beside the leader's share, as a finger's: a held-out lab read "sd 0.21
        # mm / 0.84 deg" of a leader that held 5 %, 154 degrees off the truth
        belief = belief_text(est.position_sd, est.heading_sd, est.mode_mass)
        state = "converged" if est.converged else "not converged"
        print(f"estimate  {_pose_text(est.pose)}  ({belief}; {state})")
    steps = len(report.result.steps)
    s = report.score
    if report.result.fault is not None:
        print(f"result    {fault_result(report.result.fault, steps)}")
    elif report.result.interrupted is not None:
        print(f"result    {interrupted_result(report.result.interrupted, steps)}")
    elif report.result.dropped:
        print(f"result    DROPPED the object at step {steps}")
    elif not report.truth_known:
        print(f"result    {'converged' if report.result.converged else 'not converged'} "
              f"after {steps_text(steps)} (not scored: the truth is unknown)")
    elif s.success:
        print(f"result    localized in {steps_text(steps)}: position error "
              f"{s.position_error * 1e3:.2f} mm, heading error "
              f"{math.degrees(s.heading_error):.1f} deg")
    elif s.wrong_declaration:
        print(f"result    WRONG: converged after {steps_text(steps)} on a pose "
              f"{s.position_error * 1e3:.1f} mm / {math.degrees(s.heading_error):.1f} deg away")
    elif report.result.stuck:
        print(f"result    not localized after {steps_text(steps)}: {NO_SAFE_MOVE}")
    else:
        why = why_not_converged(
            candidates=0 if est is None else est.candidates, steps=steps,
            max_steps=report.settings.max_steps, pose=None if est is None else est.pose,
            mode_mass=None if est is None else est.mode_mass,
            runner_up=None if est is None else est.runner_up,
            runner_up_mass=None if est is None else est.runner_up_mass, second="z",
            where="of the object in the hand", held_back="" if est is None else est.held_back)
        print(f"result    not localized after {steps_text(steps)}: {why}")
    if math.isfinite(report.min_quality):
        margin = report.settings.margin_n
        print(f"grasp     least quality {_beside(report.min_quality, margin)} N, "
              + (f"below the {margin:g} N margin: the object slipped"
                 if report.result.dropped else f"held above the {margin:g} N margin"))


def _beside(value: float, bound: float) -> str:
    """`value` to two decimals, or to as many as tell it from `bound` (a drop at 0.196 N
    read "least quality 0.20 N, below the 0.2 N margin")."""
    for digits in range(2, 6):
        text = f"{value:.{digits}f}"
        if (float(text) < bound) == (value < bound) and float(text) != bound:
            return text
    return f"{value:.6g}"
