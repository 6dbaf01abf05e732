"""`haptic bench soak`: the daemon under a long, ordinary load (issue 12's must-show).

`hapticd` runs as its own process (B4's scenario: the simulator at 200 Hz, B2 episodes
back to back) with subscriber *processes* on its stream: one steady reader that also times
the loop from the `state` stream (every tick publishes one, stamped with the tick's start),
some reconnecting every few seconds, one stuck (never reads). A controller here holds the
lease with `ping` (20 Hz by default), counting any request left unanswered, and samples the resident
memory of the daemon and its compute process every second.

    haptic bench soak --duration 600 --json soak.json

Reported: ticks, overruns (the daemon's own count, whole run), period p50/p99/max (from the
steady reader: every tick), gaps and messages per subscriber kind, episodes, unanswered
requests, RSS at the start, half way and the end with the second half's slope. Exit status
1 when a gap, an unanswered request or a dead daemon was seen (timing targets are for the
reader: they depend on the machine).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from service.daemon.config import DaemonConfig
from service.errors import ConfigError
from service.wire.client import Client, CommandFailed, CommandTimeout
from tools import bench_service
from tools.arg_types import integer, number
from tools.bench_common import write_json
from tools.outputs import check_outputs
from tools.wake_floor import wake_floor


def add_arguments(parser: argparse.ArgumentParser) -> None:
    bench_service.add_arguments(parser)  # the daemon's scenario, rate, --json
    parser.set_defaults(duration=600.0, subscribers=7)
    parser.add_argument("--reconnecting", type=integer(0, 256), default=5,
                        help="subscribers that reconnect (default: %(default)s; of "
                             "--subscribers, which also counts one steady and one stuck)")
    parser.add_argument("--floor-s", type=number(0.0, 86_400, "s"), default=10.0,
                        help="seconds of the same loop with empty ticks, measured first: the "
                             "machine's own timing floor (default: %(default)s)")
    parser.add_argument("--reconnect-s", type=number(0.01, 3600, "s"), default=2.0,
                        help="seconds between a reconnecting subscriber's connections")


def rss_mb(pid: int) -> float | None:
    """Resident memory of a process and its children (the compute process), MB; None when
    /proc cannot tell (not Linux, or gone)."""
    total = 0
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        for p in [pid, *map(int, children)]:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
    except (OSError, ValueError):
        return None
    return total / 1024


def _subscriber(mode: str, endpoint: str, duration: float, reconnect_s: float
                ) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tools.soak_subscriber", mode, endpoint,
                             f"{duration}", f"{reconnect_s}"], stdout=subprocess.PIPE,
                            text=True)


def _load() -> str:
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return "unknown"


def memory_trend(samples: list[tuple[float, float]]) -> dict[str, float | None]:
    """RSS at the start, half way and the end, and the second half's slope (MB/min)."""
    if len(samples) < 4:
        return {"start_mb": None, "half_mb": None, "end_mb": None,
                "second_half_mb_per_min": None}
    t = np.array([s[0] for s in samples])
    mb = np.array([s[1] for s in samples])
    half = t >= t[0] + (t[-1] - t[0]) / 2
    slope = float(np.polyfit(t[half] / 60, mb[half], 1)[0]) if half.sum() > 1 else None
    return {"start_mb": float(mb[0]), "half_mb": float(mb[half][0]), "end_mb": float(mb[-1]),
            "second_half_mb_per_min": slope}


def _episode(status: dict[str, Any]) -> int:
    """The latest episode a `status` reply shows. Its estimate is nil from an episode's start
    to its first belief, so the soak keeps the most any read showed: one read at the end
    counted 0 episodes under load."""
    return int((status.get("estimate") or {}).get("episode", 0))


def soak(args: argparse.Namespace) -> dict[str, Any]:
    load_before = _load()
    floor = wake_floor(args.rate, args.floor_s, DaemonConfig().loop.realtime_priority)
    with bench_service.daemon_process(args) as (proc, pub, cmd):
        ctl = Client(cmd, timeout_s=60.0, retries=0)
        subs: list[subprocess.Popen] = []
        unanswered = refused = pings = episodes = 0
        memory: list[tuple[float, float]] = []
        try:
            bench_service.wait_configured(ctl)
            modes = (["steady"] + ["reconnecting"] * args.reconnecting
                     + ["stuck"] * (args.subscribers - 1 - args.reconnecting))
            subs = [_subscriber(m, pub, args.duration + 2.0, args.reconnect_s) for m in modes]
            ctl.call("activate")
            ctl.call("start_exploration", repeat=True)  # answered with the first belief
            ctl.call("reset_stats")
            ctl.timeout_s = 2.0
            t0 = time.monotonic()
            next_rss = t0
            while time.monotonic() < t0 + args.duration and proc.poll() is None:
                pings += 1
                try:
                    ctl.call("ping")
                except CommandTimeout:
                    unanswered += 1
                except CommandFailed:
                    refused += 1
                now = time.monotonic()
                if now >= next_rss:
                    with contextlib.suppress(CommandTimeout, CommandFailed):
                        episodes = max(episodes, _episode(ctl.status()))
                    mb = rss_mb(proc.pid)
                    if mb is not None:
                        memory.append((now - t0, mb))
                    next_rss += 1.0
                time.sleep(max(0.0, 1.0 / args.ping_hz - (time.monotonic() - now)))
            alive = proc.poll() is None
            status = ctl.status() if alive else None
        finally:
            ctl.close()
            seen = [json.loads(s.communicate(timeout=args.duration + 60)[0] or "{}")
                    for s in subs]
    if status is None:
        raise ConfigError("hapticd died during the soak (see its log above)")
    t = status["timing"]
    steady = next((s for s in seen if s.get("mode") == "steady"), {})
    by_mode = {m: [s for s in seen if s.get("mode") == m] for m in ("reconnecting", "stuck")}
    return {
        "scenario": "soak", "duration_s": args.duration, "rate_hz": args.rate,
        "load_before": load_before, "load_after": _load(),
        "subscribers": {"steady": 1, "reconnecting": args.reconnecting,
                        "stuck": args.subscribers - 1 - args.reconnecting},
        "ticks": t["ticks"], "overruns": t["overruns"],
        "overrun_percent": 100.0 * t["overruns"] / max(1, t["ticks"]),
        "skipped_periods": t["skipped"], "period_ms": steady.get("period_ms"),
        "periods_timed": steady.get("periods", 0),
        "tick_work_ms": {"p99": t["work_p99_ms"], "max": t["work_max_ms"]},
        "localizer_update_ms": {"p99": t["localizer_p99_ms"], "max": t["localizer_max_ms"]},
        "episodes": max(episodes, _episode(status)),
        "gaps": sum(s.get("gaps", 0) for s in seen),
        "received": {"steady": steady.get("received", 0),
                     "reconnecting_min": min((s.get("received", 0)
                                              for s in by_mode["reconnecting"]), default=0)},
        "connections": sum(s.get("connections", 0) for s in seen),
        "subscribers_reporting": len([s for s in seen if s]),
        "unanswered": unanswered, "refused": refused, "pings": pings,
        "rss": memory_trend(memory), "cores": os.cpu_count(),
        "loop_scheduling": status.get("loop_scheduling"), "empty_loop_floor": floor,
    }


def run(args: argparse.Namespace) -> int:
    check_outputs(args.json)
    if (not args.duration > 0 or not args.rate > 0 or args.reconnect_s <= 0
            or not args.floor_s > 0):
        raise ConfigError("--duration, --rate, --reconnect-s and --floor-s must be > 0")
    if not 0 <= args.reconnecting <= args.subscribers - 2:
        raise ConfigError("--subscribers counts one steady and one stuck subscriber besides "
                          "the --reconnecting ones: make it at least --reconnecting + 2")
    r = soak(args)
    p, m = r["period_ms"] or {}, {k: "?" if v is None else f"{v:.1f}" for k, v in r["rss"].items()}
    print(f"soak {r['duration_s']:g} s at {r['rate_hz']:g} Hz, {r['subscribers']}: "
          f"{r['ticks']} ticks, {r['overruns']} overruns ({r['overrun_percent']:.3f} %), "
          f"period p50 {p.get('p50', float('nan')):.3f} p99 {p.get('p99', float('nan')):.3f} "
          f"max {p.get('max', float('nan')):.3f} ms, tick work p99 {r['tick_work_ms']['p99']:.3f} "
          f"ms; {r['episodes']} episodes; "
          f"{r['gaps']} gaps over {r['connections']} connections; {r['unanswered']} "
          f"unanswered; RSS {m['start_mb']} -> {m['half_mb']} -> {m['end_mb']} MB "
          f"(second half {m['second_half_mb_per_min']} MB/min); load {r['load_before']} "
          f"-> {r['load_after']}")
    f, s = r["empty_loop_floor"], r["loop_scheduling"] or {}
    print(f"the loop's thread: {s.get('policy', '?')} {s.get('priority', '')}"
          f"{' (' + s['note'] + ')' if s.get('note') else ''}; the same loop with empty "
          f"ticks on this machine just before ({args.floor_s:g} s, {f['scheduling']}): period p50 "
          f"{f['period_p50_ms']:.3f} p99 {f['period_p99_ms']:.3f} max {f['period_max_ms']:.3f} ms")
    write_json(args.json, r)
    ok = (r["gaps"] == 0 and r["unanswered"] == 0 and r["refused"] == 0
          and r["subscribers_reporting"] == args.subscribers)
    return 0 if ok else 1
