"""B4 `service`: the daemon's real-time loop under load (BENCHMARKS.md).

`hapticd` runs as its own process with the simulated backend at 200 Hz, localizing B2
episodes (noise, continuous pose) back to back. The run is made twice: with no subscriber,
and with N subscribers of which one never reads (its queue fills and PUB drops for it
alone). A controller in this process keeps the lease and times `ping` round trips; the
daemon reports tick period, overruns and the localizer's time per update (in its compute
process, outside the ticks) over the measured window.

    haptic bench service --duration 60 --json b4.json
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zmq

from service.daemon.config import BackendConfig, LoopConfig, ScenarioConfig
from service.errors import ConfigError
from service.registry import LOCALIZERS, POLICIES
from service.wire.client import Client, CommandTimeout, Subscriber
from tools.arg_types import integer, number, setting
from tools.bench_common import percentile, write_json
from tools.outputs import check_outputs

SCENARIO = """
[scenario]
localizer = "{algorithm}"
policy = "{policy}"
noise = true
max_steps = 60
seed = {seed}
[loop]
rate_hz = {rate}
[endpoints]
pub = "{pub}"
cmd = "{cmd}"
[lease]
ttl_s = 5.0
"""
"""B4's daemon apart from its backend: B2 episodes at `rate`, on ipc endpoints."""
CONFIG = """
[backend]
name = "sim"
step_duration_s = {step_s}
""" + SCENARIO


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=number(0.1, 86_400, "s"), default=60.0,
                        help="seconds measured per run (default: %(default)s)")
    parser.add_argument("--rate", type=setting(LoopConfig, "rate_hz"), default=200.0,
                        help="loop rate, Hz")
    parser.add_argument("--subscribers", type=integer(1, 256), default=10,
                        help="subscribers in the loaded run, one of which never reads")
    parser.add_argument("--step-s", type=setting(BackendConfig, "step_duration_s"), default=0.02,
                        help="simulated step duration, s (default: %(default)s)")
    parser.add_argument("--seed", type=setting(ScenarioConfig, "seed"), default=0)
    parser.add_argument("--algorithm", default=ScenarioConfig.localizer,
                        choices=LOCALIZERS.names(),
                        help="the daemon's localizer (default: %(default)s, its own default)")
    parser.add_argument("--policy", default=ScenarioConfig.policy, choices=POLICIES.names(),
                        help="the daemon's policy (default: %(default)s)")
    parser.add_argument("--ping-hz", type=number(0.1, 1000, "Hz"), default=20.0,
                        help="command round trips timed per second")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")


class Reader(threading.Thread):
    """A subscriber that reads and decodes everything, counting messages and gaps."""

    def __init__(self, endpoint: str, ctx: zmq.Context) -> None:
        super().__init__(daemon=True)
        self.sub = Subscriber(endpoint, ctx=ctx)
        self.stop = threading.Event()
        self.episodes_done = 0

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.sub.recv(0.1)
            if msg is not None and msg.topic == "event" and msg["event"] == "episode_done":
                self.episodes_done += 1
        self.sub.close()


def _percentiles(values: list[float]) -> dict[str, float | None]:
    return {"p50": percentile(values, 50), "p99": percentile(values, 99),
            "max": max(values, default=None)}


@contextmanager
def daemon_process(args: argparse.Namespace, template: str = CONFIG, **fields: Any
                   ) -> Iterator[tuple[subprocess.Popen, str, str]]:
    """`hapticd` as its own process with B4's scenario (or `template` filled with `fields`)
    on ipc endpoints: (process, pub, cmd); stopped with SIGTERM (killed if it does not
    stop) on exit."""
    with tempfile.TemporaryDirectory(dir="/tmp", prefix="b4-") as tmp:
        pub, cmd = f"ipc://{tmp}/pub", f"ipc://{tmp}/cmd"
        cfg = Path(tmp) / "hapticd.toml"
        cfg.write_text(template.format(step_s=args.step_s, seed=args.seed, rate=args.rate,
                                       algorithm=args.algorithm, policy=args.policy,
                                       pub=pub, cmd=cmd, **fields))
        proc = subprocess.Popen([sys.executable, "-m", "service.daemon.main", "--config", str(cfg),
                                 "--log-level", "warning"])
        try:
            yield proc, pub, cmd
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def wait_configured(ctl: Client, timeout_s: float = 120.0) -> None:
    """Until the daemon's start-up configure is done (it answers meanwhile). A daemon that
    is still starting (importing, on a loaded machine) is asked again until `timeout_s`:
    a held-out check's bench at load 5 gave up after one try of 20 s."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            status = ctl.status()
        except CommandTimeout:
            if time.monotonic() > end:
                raise
            continue
        if status["state"] != "unconfigured" and not status.get("configuring"):
            return
        if time.monotonic() > end:
            raise ConfigError(f"hapticd did not configure within {timeout_s:g} s "
                              f"(state {status['state']})")
        time.sleep(0.1)  # polling a daemon that is busy elsewhere, not synchronizing


def measure(subscribers: int, args: argparse.Namespace) -> dict[str, Any]:
    """One run of the daemon with `subscribers` subscribers (one stuck if any)."""
    with daemon_process(args) as (proc, pub, cmd):
        ctx = zmq.Context()
        readers: list[Reader] = []
        stuck = None
        ctl = Client(cmd, ctx=ctx, timeout_s=20.0, retries=0)
        try:
            wait_configured(ctl)
            if subscribers > 0:
                stuck = ctx.socket(zmq.SUB)  # connected, subscribed, never read
                stuck.setsockopt(zmq.SUBSCRIBE, b"")
                stuck.connect(pub)
                readers = [Reader(pub, ctx) for _ in range(subscribers - 1)]
                for r in readers:
                    r.start()
            ctl.call("activate")
            ctl.call("start_exploration", repeat=True)  # answered with the first belief
            ctl.call("reset_stats")
            ctl.timeout_s = 2.0
            rtts: list[float] = []
            end = time.monotonic() + args.duration
            period = 1.0 / args.ping_hz
            next_ping = time.monotonic()
            while time.monotonic() < end:
                t0 = time.perf_counter()
                ctl.call("ping")
                rtts.append((time.perf_counter() - t0) * 1e3)
                next_ping += period
                time.sleep(max(0.0, next_ping - time.monotonic()))
            status = ctl.status()
        finally:
            ctl.close()  # (an open socket would keep ctx.term() waiting for ever)
            for r in readers:
                r.stop.set()
            for r in readers:
                r.join(5)
            if stuck is not None:
                stuck.close(linger=0)
            ctx.term()
    t = status["timing"]
    gaps = [sum(r.sub.gaps.values()) for r in readers]
    received = [sum(r.sub.received.values()) for r in readers]
    return {
        "subscribers": subscribers, "stuck_subscribers": 1 if subscribers else 0,
        "duration_s": args.duration, "rate_hz": args.rate, "ticks": t["ticks"],
        "period_ms": {"p50": t["period_p50_ms"], "p99": t["period_p99_ms"],
                      "max": t["period_max_ms"]},
        "overruns": t["overruns"], "skipped_periods": t["skipped"],
        "tick_work_ms": {"p50": t["work_p50_ms"], "p99": t["work_p99_ms"],
                         "max": t["work_max_ms"]},
        "localizer_update_ms": {"p99": t["localizer_p99_ms"], "max": t["localizer_max_ms"]},
        # the status's own count: its estimate is nil from an episode's start to its first
        # belief, and a run that asked just then counted 0 episodes (a `make test`)
        "episodes_started": status["episode"],
        "published": status["published"],
        "reader_received": {"min": min(received, default=0), "max": max(received, default=0)},
        "reader_gaps": {"min": min(gaps, default=0), "max": max(gaps, default=0)},
        "command_rtt_ms": _percentiles(rtts), "commands_timed": len(rtts),
    }


def run(args: argparse.Namespace) -> int:
    check_outputs(args.json)
    if not args.duration > 0 or not args.rate > 0 or args.subscribers < 2:
        raise ConfigError("--duration and --rate must be > 0 and --subscribers >= 2")
    results = [measure(0, args), measure(args.subscribers, args)]
    for r in results:
        p, w = r["period_ms"], r["localizer_update_ms"]
        rtt = r["command_rtt_ms"]
        print(f"{r['subscribers']:>2} subscribers ({r['stuck_subscribers']} stuck): "
              f"period p50 {p['p50']:.3f} p99 {p['p99']:.3f} max {p['max']:.3f} ms, "
              f"overruns {r['overruns']} of {r['ticks']} ticks, "
              f"localizer update p99 {w['p99']:.3f} ms"
              f", episodes {r['episodes_started']}, published {sum(r['published'].values())}"
              f", reader gaps {r['reader_gaps']['max']}, rtt p50 {rtt['p50']:.3f} "
              f"p99 {rtt['p99']:.3f} ms")
    write_json(args.json, {"scenario": "service", "runs": results})
    return 0
