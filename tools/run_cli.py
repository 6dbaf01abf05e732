"""`haptic run`: one localization episode, narrated step by step (what `make demo` runs)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

from firmware_if.backend import Backend
from service.episode.runner import StepRecord
from service.episode.scenario import (
    RunSettings,
    Truth,
    check_scenario,
    for_backend,
)
from service.episode.simulate import EpisodeReport, simulate
from service.errors import ConfigError
from service.localization.map_check import check_map
from service.localization.maps import load_map
from service.localization.policies.base import MOVE_NAMES
from service.registry import BACKENDS
from tools.hand_cli import add_object_options, object_options_given, run_hand
from tools.outputs import check_outputs, write_episode
from tools.scenario_options import add_scenario_options, settings_from_args
from tools.signals import closed_whole
from tools.words import (
    belief_text,
    fault_result,
    interrupted_result,
    pose_text,
    steps_text,
    why_not_converged,
)

FIGURE_STEPS = (0, 5, 10)
"""Steps whose hypotheses `--plot` shows, besides the last (tools/plots.py)."""



def register(p: argparse.ArgumentParser) -> None:
    p.description = ("Run one localization episode and report the estimate beside the truth. "
                     "Lengths in metres, headings in degrees.")
    add_scenario_options(p, defaults=RunSettings())
    p.add_argument("--seed", type=int, default=0, help="seed for the start pose, noise and "
                   "choices (default: %(default)s)")
    p.add_argument("--start", metavar="X,Y,HEADING_DEG", default=None,
                   help="true start pose (metres, metres, degrees); default: drawn from --seed")
    p.add_argument("--plot", type=Path, metavar="FILE.png",
                   help="save a figure like the paper's Figure 4")
    p.add_argument("--json", type=Path, metavar="FILE", help="save the episode as JSON")
    p.add_argument("--quiet", action="store_true", help="no per-step lines")
    hw = p.add_argument_group("hardware")
    hw.add_argument("--backend", default="sim", choices=BACKENDS.names(),
                    help="finger to use (default: %(default)s)")
    hw.add_argument("--port", help="serial port of the servo bus (dynamixel backend)")
    hw.add_argument("--hand", help="hand preset or TOML file (dynamixel backend, or the hand "
                    "holding --object)")
    hw.add_argument("--cycle-budget", type=float, metavar="MS", default=None,
                    help="milliseconds a bus cycle may take before it counts as missed "
                         "(3 in a row end the run with a fault); raise it on a loaded "
                         "machine or a slow adapter (dynamixel backend; default: 10)")
    add_object_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    budget = cycle_budget_option(args)  # refused before anything else is done
    if args.object is not None:
        return run_hand(args, budget)
    stray = object_options_given(args)
    if stray:
        raise ConfigError(f"{', '.join(stray)} appl{'ies' if len(stray) == 1 else 'y'} to a "
                          "hand holding an object: give --object NAME, or leave "
                          f"{'it' if len(stray) == 1 else 'them'} out")
    if args.port is not None and args.backend == "sim":
        raise ConfigError("--port is a servo bus's: it needs --backend dynamixel")
    if args.hand is not None and args.backend == "sim":
        raise ConfigError(f"--hand {args.hand} without --object: a simulated finger on a map "
                          "needs no hand; give --object NAME for a hand holding an object, or "
                          "--backend dynamixel --port PORT for a finger on servos")
    settings = settings_from_args(args)
    check_outputs(args.json, figures=(args.plot,), inputs=(args.map,))
    if args.backend != "sim":  # refused before any line of the run is printed
        from firmware_if.dxl_bus import check_port_exists  # the SDK only for servos

        if not args.port or not args.hand:
            raise ConfigError(f"--backend {args.backend} needs --port and --hand")
        check_port_exists(args.port)
    height_map = load_map(settings.map, settings.spacing)
    check_scenario(settings, height_map)
    for warning in check_map(height_map, settings.radius, settings.step).warnings:
        print(f"warning: {warning}")
    backend_factory: Callable[[Truth], Backend] | None = None
    if args.backend != "sim":
        settings = for_backend(settings, args.backend, args.hand)
        cls = BACKENDS.load(args.backend)

        def backend_factory(truth: Truth) -> Backend:
            """A hardware hand; the truth is not its to know (the emulator draws its own)."""
            return closed_whole(cls.from_cli(port=args.port, hand=args.hand,
                                             radius=settings.radius, step=settings.step,
                                             **budget))
    size = (f"profile of {height_map.shape[1]} samples, {height_map.extent[0] * 1e3:.0f} mm "
            "long" if height_map.is_profile else
            f"{height_map.shape[1]} x {height_map.shape[0]} samples, "
            f"{height_map.extent[0] * 1e3:.0f} x {height_map.extent[1] * 1e3:.0f} mm")
    print(f"map {height_map.name}: {size}; "
          f"finger radius {settings.radius * 1e3:g} mm, step {settings.step * 1e3:g} mm; "
          f"{settings.algorithm} + {settings.policy}{' with noise' if settings.noise else ''}")
    report = simulate(settings, height_map, on_step=None if args.quiet else StepPrinter(),
                      snapshot_steps=FIGURE_STEPS if args.plot else (),
                      backend_factory=backend_factory, keep_on_interrupt=True)
    _print_summary(report)
    return write_episode(report, args.json, args.plot, _draw,
                         failed=report.score.wrong_declaration)


def _draw(report: EpisodeReport, path: Path) -> None:
    from tools.plots import episode_figure

    episode_figure(report, path)


class StepPrinter:
    """One line per step: the move, this step's height change, how sure the localizer is."""

    def __init__(self) -> None:
        self.z = 0.0
        print("dz: this step's height change (z: relative to the start). spread: sd of the "
              "estimate's position / heading\n(over all hypotheses until a pose fits the "
              "readings, then that pose's own; unbounded: the readings so far, on a plain, "
              "let it slide). leading mode: the best pose's share among the poses the "
              "localizer weighs (not a checked chance: only a declared pose is checked "
              "against the whole map).")

    def __call__(self, step: StepRecord) -> None:
        move = MOVE_NAMES[step.move] + (" (blocked)" if step.blocked else "")
        z = step.measurement[2]
        dz, self.z = z - self.z, z
        belief = belief_text(step.position_sd, step.heading_sd, step.mode_mass)
        print(f"step {step.index:3d}  move {move:<12} dz {dz * 1e3:+7.3f} mm "
              f"(z {z * 1e3:+7.3f} mm)  {belief:<44} {step.compute_ms:6.2f} ms", flush=True)


def _print_summary(report: EpisodeReport) -> None:
    est = report.result.estimate
    steps = len(report.result.steps)
    print(f"truth     {pose_text(report.truth.as_tuple())}")
    if est is None or est.pose is None:
        print("estimate  none: every hypothesis was eliminated")
    else:
        belief = belief_text(est.position_sd, est.heading_sd, est.mode_mass)
        state = "converged" if est.converged else "not converged"
        print(f"estimate  {pose_text(est.pose)}  ({belief}; {state})")
    s = report.score
    if report.result.fault is not None:
        print(f"result    {fault_result(report.result.fault, steps)}")
    elif report.result.interrupted is not None:
        print(f"result    {interrupted_result(report.result.interrupted, steps)}")
    elif s.success:
        print(f"result    localized in {steps_text(steps)}: position error "
              f"{s.position_error * 1e3:.2f} mm, "
              f"heading error {math.degrees(s.heading_error):.1f} deg")
    elif s.wrong_declaration:
        print(f"result    WRONG: converged after {steps_text(steps)} on a pose "
              f"{s.position_error * 1e3:.1f} mm / {math.degrees(s.heading_error):.1f} deg away")
    else:
        why = why_not_converged(
            candidates=0 if est is None else est.candidates, steps=steps,
            max_steps=report.settings.max_steps, pose=None if est is None else est.pose,
            mode_mass=None if est is None else est.mode_mass,
            runner_up=None if est is None else est.runner_up,
            runner_up_mass=None if est is None else est.runner_up_mass,
            held_back="" if est is None else est.held_back,
            where=("of its pose table (a start between the table's poses fits none: `particles` "
                   "searches the whole map)" if report.settings.algorithm == "elimination"
                   else "on this map"))
        print(f"result    not localized after {steps_text(steps)}: {why}")
        if est is not None and est.pose is not None and s.position_error is not None:
            print(f"          (the leading pose is {s.position_error * 1e3:.1f} mm / "
                  f"{math.degrees(s.heading_error):.1f} deg from the truth)")
    if report.true_pose_eliminated:
        print("warning   the true pose was eliminated")


def cycle_budget_option(args: argparse.Namespace) -> dict[str, float]:
    """`--cycle-budget` as a backend's `cycle_budget_s` (nothing when not given), checked
    before anything runs; refused for the simulator, which has no bus."""
    if args.cycle_budget is None:
        return {}
    if args.backend == "sim":
        raise ConfigError("--cycle-budget is a servo bus's: it needs --backend dynamixel")
    if not 2.0 <= args.cycle_budget <= 500.0:
        raise ConfigError(f"--cycle-budget must be 2 .. 500 ms, got {args.cycle_budget:g}")
    return {"cycle_budget_s": args.cycle_budget / 1e3}
