"""Bus cycle time on the emulator: one Sync Read + one Sync Write of 3 servos, p50/p99.

Both read paths are timed in the same run (Fast Sync Read and plain Sync Read), so their
ratio is meaningful. Run as `haptic bench bus`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from firmware_if.dxl_bus import DxlBus
from firmware_if.errors import CommunicationError
from sim_backend.emulator import EmulatedServo, ServoBus
from tools.arg_types import integer
from tools.bench_common import write_json
from tools.outputs import check_outputs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cycles", type=integer(1, 1_000_000), default=2000, metavar="N",
                        help="cycles timed per read path (default: %(default)s)")
    parser.add_argument("--servos", type=integer(1, 252), default=3, metavar="N",
                        help="servos on the bus (default: %(default)s)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")


def measure(servos: int = 3, cycles: int = 2000, fast: bool = True) -> dict[str, Any]:
    """Cycle times (ms) of `cycles` sync read + sync write cycles on a fresh emulator."""
    ids = tuple(range(1, servos + 1))
    with ServoBus([EmulatedServo(i) for i in ids]) as emu, DxlBus(emu.port, ids) as bus:
        bus.configure({"return_delay_time": 0, "operating_mode": 5})
        bus.use_fast_read = fast
        used_fast = bus.detect_fast_read()
        bus.torque(True)
        times = np.full(cycles, np.nan)
        for k in range(cycles):
            goals = {sid: 2048 + (k % 200) for sid in ids}
            t0 = time.perf_counter_ns()
            try:
                bus.cycle(goals)
            except CommunicationError:  # missed (counted in `failures`); a latched fault ends it
                continue
            times[k] = (time.perf_counter_ns() - t0) / 1e6
        bus.torque(False)
        times = times[np.isfinite(times)]
    return {"read": "fast sync read" if used_fast else "sync read", "servos": servos,
            "cycles": cycles, "p50_ms": float(np.percentile(times, 50)),
            "p99_ms": float(np.percentile(times, 99)), "max_ms": float(times.max()),
            "failures": bus.stats.failures}


def run(args: argparse.Namespace) -> int:
    check_outputs(args.json)
    results = [measure(args.servos, args.cycles, fast=True),
               measure(args.servos, args.cycles, fast=False)]
    for r in results:
        print(f"{r['read']:>15s}: {r['servos']} servos, {r['cycles']} cycles: "
              f"p50 {r['p50_ms']:.3f} ms, p99 {r['p99_ms']:.3f} ms, max {r['max_ms']:.3f} ms, "
              f"failures {r['failures']}")
    ratio = results[1]["p50_ms"] / results[0]["p50_ms"]
    print(f"sync read / fast sync read p50 ratio: {ratio:.2f}")
    write_json(args.json, {"scenario": "bus", "results": results,
                           "p50_ratio_plain_over_fast": ratio})
    return 0
