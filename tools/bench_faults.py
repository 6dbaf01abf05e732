"""`haptic bench faults`: kill the servo bus under a running daemon, again and again.

`haptic emulate` serves a hand's servo bus on a pty behind a stable symlink (as udev's
/dev/serial/by-id/... names a USB adapter); `hapticd` runs as its own process on it with
the Dynamixel backend. Each round the daemon explores until the finger moves, the
emulator process is killed (SIGKILL: the port vanishes mid-exchange), and the round
passes when the daemon latches a `fault` (torque off, no exploring), still answers,
and `reset` brings it back to `inactive` on a new emulator at the same path. After the
last round it explores again (the touch-down needs the goal current `open` wrote).

    haptic bench faults --rounds 20 --json faults.json

Exit status 1 unless every round passed.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from firmware_if.hand import presets
from service.daemon.config import LoopConfig, ScenarioConfig
from service.errors import ConfigError
from service.wire.client import CommandFailed, CommandTimeout, Controller, Subscriber
from tools import bench_service
from tools.arg_types import integer, setting
from tools.bench_common import percentile, write_json
from tools.outputs import check_outputs

CONFIG = """
[backend]
name = "dynamixel"
options = {{ port = "{port}", hand = "{hand}", cycle_budget_s = 0.05 }}
""" + bench_service.SCENARIO


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rounds", type=integer(1, 10_000), default=20,
                        help="emulator kills (default: %(default)s)")
    parser.add_argument("--hand", default="spatial", choices=presets(),
                        help="hand preset (default: %(default)s)")
    parser.add_argument("--seed", type=setting(ScenarioConfig, "seed"), default=3,
                        help="the hidden start pose's seed")
    parser.add_argument("--rate", type=setting(LoopConfig, "rate_hz"), default=200.0,
                        help="loop rate, Hz")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures as JSON")
    parser.set_defaults(step_s=0.0, algorithm=ScenarioConfig.localizer,
                        policy=ScenarioConfig.policy)


class Emulator:
    """`haptic emulate` as a process of its own, at `link`."""

    def __init__(self, hand: str, seed: int, link: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "emulate", "--hand", hand, "--seed", str(seed),
             "--link", str(link)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()  # its port: it is serving
        if not line:
            raise ConfigError(f"haptic emulate did not start: {self.proc.stderr.read()[-500:]}")

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait(10)
        self.proc.stdout.close()
        self.proc.stderr.close()


def _explore_until_moving(sub: Subscriber, ctl: Controller) -> bool:
    if sub.wait_for(lambda m: m.topic == "state" and m["state"] == "inactive"
                    and m["fingers"], 30.0) is None:
        return False
    ctl.call("activate")
    ctl.call("start_exploration", repeat=True)
    return sub.wait_for(lambda m: m.topic == "state" and m["moving"], 30.0) is not None


def one_round(sub: Subscriber, ctl: Controller, daemon: subprocess.Popen,
              emulators: list[Emulator], args: argparse.Namespace, link: Path
              ) -> dict[str, Any]:
    """Explore, kill the bus, expect a fault, reset onto a new emulator."""
    out: dict[str, Any] = {"moving": _explore_until_moving(sub, ctl)}
    t0 = time.monotonic()
    emulators[-1].kill()
    fault = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "fault", 10.0)
    out["fault_ms"] = None if fault is None else (time.monotonic() - t0) * 1e3
    out["reason"] = None if fault is None else fault["reason"]
    state = sub.wait_for(lambda m: m.topic == "state" and m["state"] == "fault", 5.0)
    out["torque_off"] = state is not None and not state["torque_on"] and not state["exploring"]
    out["alive"] = daemon.poll() is None and ctl.call("ping") == {"pong": True}
    emulators.append(Emulator(args.hand, args.seed, link))
    t1 = time.monotonic()
    try:
        out["reset"] = ctl.call("reset")["state"] == "inactive"
    except (CommandFailed, CommandTimeout) as exc:
        out["reset"], out["reset_error"] = False, str(exc)
    out["reset_ms"] = (time.monotonic() - t1) * 1e3
    out["passed"] = all(out[k] for k in ("moving", "torque_off", "alive", "reset")) \
        and fault is not None
    return out


def campaign(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="faults-") as tmp:
        link = Path(tmp) / "ttyDXL"
        emulators = [Emulator(args.hand, args.seed, link)]
        rounds: list[dict[str, Any]] = []
        try:
            with bench_service.daemon_process(args, CONFIG, port=str(link), hand=args.hand) \
                    as (daemon, pub, cmd), Subscriber(pub, ["state", "event"]) as sub, \
                    Controller(cmd, timeout_s=60.0, retries=0) as ctl:
                bench_service.wait_configured(ctl)
                ctl.timeout_s = 10.0
                for i in range(args.rounds):
                    r = one_round(sub, ctl, daemon, emulators, args, link)
                    rounds.append(r)
                    print(f"round {i + 1}: {'passed' if r['passed'] else 'FAILED'}, fault "
                          f"after {_ms(r['fault_ms'])} ({r['reason']}), reset "
                          f"{_ms(r['reset_ms'])}", flush=True)
                    if not r["alive"]:
                        break
                explores_after = _explore_until_moving(sub, ctl)
                ctl.call("deactivate")
        finally:
            for e in emulators:
                if e.proc.poll() is None:
                    e.kill()
    faults = [r["fault_ms"] for r in rounds if r["fault_ms"] is not None]
    resets = [r["reset_ms"] for r in rounds if r["reset"]]
    return {
        "scenario": "faults", "hand": args.hand, "rounds": len(rounds),
        "passed": sum(r["passed"] for r in rounds),
        "faults_latched": len(faults), "daemon_alive": all(r["alive"] for r in rounds),
        "resets_ok": len(resets), "explores_after": explores_after,
        "fault_ms": {"p50": percentile(faults, 50), "max": max(faults, default=None)},
        "reset_ms": {"p50": percentile(resets, 50), "max": max(resets, default=None)},
        "each": rounds,
    }


def run(args: argparse.Namespace) -> int:
    check_outputs(args.json)
    if args.rounds < 1:
        raise ConfigError("--rounds must be at least 1")
    r = campaign(args)
    print(f"{r['passed']}/{r['rounds']} rounds passed: {r['faults_latched']} faults latched, "
          f"daemon {'up' if r['daemon_alive'] else 'DOWN'}, {r['resets_ok']} resets onto a "
          f"new emulator, explores afterwards: {r['explores_after']}; fault after p50 "
          f"{_ms(r['fault_ms']['p50'])} max {_ms(r['fault_ms']['max'])}, reset p50 "
          f"{_ms(r['reset_ms']['p50'])} max {_ms(r['reset_ms']['max'])}")
    write_json(args.json, r)
    return 0 if r["passed"] == args.rounds == r["rounds"] and r["explores_after"] else 1


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f} ms"
