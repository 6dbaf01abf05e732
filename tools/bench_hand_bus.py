"""A hand on the servo-bus emulator (issue 10): the bus read per tick for the whole hand, and
seeded episodes through the bus beside the same episodes simulated.

Ticks: `read_hand` of `DynamixelHand` on `haptic emulate --object`'s bus, idle, with Fast Sync
Read and with plain Sync Read in the same run (their ratio is meaningful), p50/p99, and how
many instruction packets the emulator received per tick. Episodes: for each seed, the
simulated run and the run through the bus (`haptic run --object` both ways), their outcomes,
steps, declared or leading poses and wall times. Run as `haptic bench hand-bus`.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from firmware_if.dxl_bus import TORQUE_CHECK_CYCLES
from firmware_if.dynamixel_hand import DynamixelHand
from service.episode.hand_episode import HandEpisodeReport, simulate_hand, simulated_hand
from service.episode.hand_scenario import HandSettings, load_parts
from sim_backend.emulator import ServoBus
from sim_backend.emulator.hand_plant import HandPlant
from sim_backend.emulator.plant import hand_bus_servos
from tools.arg_types import integer
from tools.bench_common import check_seeds, write_json
from tools.outputs import check_outputs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hand", default="two-finger", help="hand preset (default: "
                        "%(default)s)")
    parser.add_argument("--object", default="keyed", help="object preset (default: "
                        "%(default)s)")
    parser.add_argument("--ticks", type=integer(1, 1_000_000), default=2000, metavar="N",
                        help="reads timed per read path (default: %(default)s)")
    parser.add_argument("--seeds", type=integer(1, 10_000), default=4, metavar="N",
                        help="seeded episodes run both ways (default: %(default)s; 0: none)")
    parser.add_argument("--first-seed", type=int, default=0, metavar="S")
    parser.add_argument("--max-steps", type=integer(1, 10_000), default=12, metavar="N")
    parser.add_argument("--noise", action="store_true", help="B2's noise on both sides")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")


def _on_bus(settings: HandSettings, parts, *, fast: bool = True) -> tuple[ServoBus, HandPlant]:
    plant = HandPlant(simulated_hand(settings, parts)[0])
    return (ServoBus(hand_bus_servos(parts.hand, plant), plant=plant, fast_read=fast).start(),
            plant)


def measure_ticks(settings: HandSettings, ticks: int, fast: bool) -> dict[str, Any]:
    """Times (ms) of `ticks` reads of the whole hand, and packets the emulator got per read."""
    parts = load_parts(settings)
    bus, _ = _on_bus(settings, parts, fast=fast)
    try:
        hand = DynamixelHand(parts.hand, bus.port)
        hand.open()
        try:
            hand.set_torque(True)
            hand.read_hand()
            before = bus.stats["rx_packets"]
            times = np.empty(ticks)
            for k in range(ticks):
                t0 = time.perf_counter_ns()
                hand.read_hand()
                times[k] = (time.perf_counter_ns() - t0) / 1e6
            packets = (bus.stats["rx_packets"] - before) / ticks
            failures = hand.bus.stats.failures
            used_fast = hand.bus.stats.fast_read
        finally:
            hand.close()
    finally:
        bus.stop()
    return {"read": "fast sync read" if used_fast else "sync read", "hand": settings.hand,
            "servos": len(parts.hand.ids), "ticks": ticks,
            "p50_ms": float(np.percentile(times, 50)), "p99_ms": float(np.percentile(times, 99)),
            "max_ms": float(times.max()), "packets_per_tick": packets, "failures": failures}


def _outcome(report: HandEpisodeReport) -> str:
    result = report.result
    if result.dropped:
        return "dropped"
    if report.score.success:
        return "localized"
    if report.score.wrong_declaration:
        return "WRONG"
    return "stuck" if result.stuck else "not yet"


def compare(settings: HandSettings) -> dict[str, Any]:
    """One seed simulated and through the bus."""
    parts = load_parts(settings)
    t0 = time.perf_counter()
    sim = simulate_hand(settings, parts)
    sim_s = time.perf_counter() - t0
    bus, plant = _on_bus(settings, parts)
    try:
        t0 = time.perf_counter()
        hil = simulate_hand(settings, parts,  # scored on the emulator's hidden object
                            backend_factory=lambda: DynamixelHand(parts.hand, bus.port),
                            hidden=plant.sim)
        hil_s = time.perf_counter() - t0
    finally:
        bus.stop()
    a, b = sim.result.estimate.pose, hil.result.estimate.pose
    turn = (a[2] - b[2] + math.pi) % (2 * math.pi) - math.pi
    same_commands = 0
    for x, y in zip(sim.result.steps, hil.result.steps, strict=False):
        if x.command != y.command and not _close(x.command, y.command):
            break
        same_commands += 1
    return {"seed": settings.seed, "sim": _outcome(sim), "bus": _outcome(hil),
            "sim_error": _error(sim), "bus_error": _error(hil),
            "turns": [sum(s.kind == "manipulate" for s in r.result.steps) for r in (sim, hil)],
            "sim_steps": len(sim.result.steps), "bus_steps": len(hil.result.steps),
            "same_first_commands": same_commands,
            "pose_gap_mm": math.hypot(a[0] - b[0], a[1] - b[1]) * 1e3,
            "heading_gap_deg": abs(math.degrees(turn)),
            "converged": [sim.result.converged, hil.result.converged],
            "sim_s": sim_s, "bus_s": hil_s, "bus_errors": len(bus.errors)}


def _error(report: HandEpisodeReport) -> list[float] | None:
    """(mm, deg) from the estimate to the object's true pose at the end."""
    s = report.score
    if s.position_error is None:
        return None
    return [s.position_error * 1e3, math.degrees(s.heading_error)]


def _close(a, b) -> bool:
    """Two commands the same but for the encoders' rounding (0.2 mm, 0.01 rad)."""
    if [m is None for m in a] != [m is None for m in b]:
        return False
    return all(m is None or np.allclose(m, n, atol=2e-4) for m, n in zip(a, b, strict=True))


def _err_text(error: list[float] | None) -> str:
    return "no estimate" if error is None else f"off by {error[0]:.2f} mm / {error[1]:.1f} deg"


def run(args: argparse.Namespace) -> int:
    check_seeds(args.first_seed, args.seeds, "--seeds")
    check_outputs(args.json)
    settings = HandSettings(object=args.object, hand=args.hand, noise=args.noise,
                            max_steps=args.max_steps)
    ticks = [measure_ticks(settings, args.ticks, fast=True),
             measure_ticks(settings, args.ticks, fast=False)]
    for r in ticks:
        print(f"{r['read']:>15s}: hand {r['hand']} ({r['servos']} servos), {r['ticks']} reads: "
              f"p50 {r['p50_ms']:.3f} ms, p99 {r['p99_ms']:.3f} ms, max {r['max_ms']:.3f} ms, "
              f"{r['packets_per_tick']:.2f} instruction packets per read (one, and a check "
              f"of torque every {TORQUE_CHECK_CYCLES}), "
              f"failures {r['failures']}")
    ratio = ticks[1]["p50_ms"] / ticks[0]["p50_ms"]
    print(f"sync read / fast sync read p50 ratio: {ratio:.2f}")
    episodes = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        e = compare(HandSettings(object=args.object, hand=args.hand, noise=args.noise,
                                 max_steps=args.max_steps, seed=seed))
        episodes.append(e)
        print(f"seed {seed}: simulated {e['sim']} after {e['sim_steps']} steps "
              f"({e['turns'][0]} turns, {_err_text(e['sim_error'])}), through the bus "
              f"{e['bus']} after {e['bus_steps']} ({e['turns'][1]} turns, "
              f"{_err_text(e['bus_error'])}); first {e['same_first_commands']} commands alike; "
              f"{e['sim_s']:.1f} s / {e['bus_s']:.1f} s", flush=True)
    same = sum(e["sim"] == e["bus"] for e in episodes)
    if episodes:
        print(f"same outcome in {same} of {len(episodes)} seeds; drops "
              f"{sum(e['bus'] == 'dropped' for e in episodes)} through the bus, "
              f"{sum(e['sim'] == 'dropped' for e in episodes)} simulated; wrong declarations "
              f"{sum('WRONG' in (e['sim'], e['bus']) for e in episodes)}")
    write_json(args.json, {"scenario": "hand-bus", "ticks": ticks,
                           "p50_ratio_plain_over_fast": ratio, "episodes": episodes,
                           "same_outcome": same})
    return 0
