"""`haptic ctl` (one command to hapticd) and `haptic explore` (one localization, start to end).

`explore` does on one connection what a controller must: wait for the daemon, take the
lease, activate, start an episode, keep the lease with a request every second while it
prints the progress, then stop, turn torque off and give the lease back, whatever ends it
(convergence, a fault, Ctrl-C). Only the connection holding the lease may control the
finger, so chained `haptic ctl activate`, `haptic ctl start_exploration` processes cannot
do this; `explore` is the one-command way.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import json
import os
import sys
import time
from typing import Any

from service.errors import InputError, ServiceError
from service.wire.client import SLOW_COMMANDS, Client, CommandFailed, CommandTimeout, Subscriber
from service.wire.commands import TABLE
from tools.arg_types import integer, number
from tools.signals import signals_held
from tools.stream_cli import add_endpoint_options, client_from, subscriber_from, unheard_words
from tools.words import (
    NO_SAFE_MOVE,
    belief_text,
    hand_step_text,
    pose_text,
    steps_text,
    why_not_converged,
)

NO_REPLY = 3
FAULTED = 4
"""`haptic explore`'s status when the daemon is or goes in fault: a script tells a fault,
which needs a person, from an honest end without a pose (1; a held-out fault campaign
could not tell them apart)."""
"""Exit status when hapticd does not answer."""
PING_S = 1.0
"""How often `explore` renews the lease (the daemon's default lease lasts 3 s)."""


# -- haptic ctl --------------------------------------------------------------------------
def register_ctl(p: argparse.ArgumentParser) -> None:
    p.description = ("Send one command to hapticd and print its result as JSON. Exit status: "
                     "0 ok, 1 the daemon refused (the message says why), 3 no reply. Control "
                     "commands take the lease for this one connection; the finger belongs "
                     "to whoever holds it, so use `haptic explore` to localize.")
    p.epilog = commands_help()
    p.add_argument("command", metavar="COMMAND", help="one of the commands listed below")
    p.add_argument("args", nargs="*", metavar="KEY=VALUE", default=[],  # optional, also
                   # to parse_intermixed_args, which without a default calls it required
                   help="the command's arguments; VALUE is JSON where it parses (3, true, "
                        "{...}), else a string. For configure, SECTION.KEY=VALUE sets one "
                        "key (scenario.seed=3)")
    p.add_argument("--client", metavar="NAME", help="a name for this controller, shown as "
                   "the lease holder (default: ctl-PID)")
    p.add_argument("--timeout", type=number(0.01, 86_400, "s"), default=None, metavar="S",
                   help="seconds to wait for each try (default: 2, and 120 for the commands "
                        "answered when slow work is done: "
                        + ", ".join(sorted(SLOW_COMMANDS)) + ")")
    p.add_argument("--retries", type=integer(0, 100), default=2, metavar="N",
                   help="resends before giving up; the daemon never runs a resent request "
                        "twice (default: %(default)s)")
    add_endpoint_options(p, pub=False)
    p.set_defaults(handler=cmd_ctl)


def commands_help() -> str:
    """The command table as help text: name, arguments, whether it needs the lease, summary."""
    lines = ["commands (* takes the lease; docs/protocol.md has results and errors):"]
    for name, spec in TABLE.items():
        args = " ".join(f"{a}={kind.rstrip('?').upper()}" if a in spec.required
                        else f"[{a}={kind.rstrip('?').upper()}]"
                        for a, kind in spec.fields.items())
        usage = f"{name} {args}".strip()
        lines.append(f"  {usage:<40} {'*' if spec.lease else ' '} {spec.summary}")
    lines += ["", "examples:", "  haptic ctl status",
              "  haptic ctl set_map map=bumps:20:3",
              "  haptic ctl configure scenario.seed=4 scenario.noise=true --client me",
              "  haptic ctl estop reason=\"hand in the way\""]
    return "\n".join(lines)


def check_command(name: str) -> None:
    if name not in TABLE:
        close = difflib.get_close_matches(name, TABLE, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise InputError(f"unknown command '{name}'; {hint}commands: {', '.join(TABLE)}")


def parse_kv(items: list[str], *, sections: bool = False) -> dict[str, Any]:
    """KEY=VALUE pairs; VALUE is JSON when it parses (numbers, true, {...}), else a string.

    With `sections`, SECTION.KEY=VALUE goes into {"changes": {SECTION: {KEY: VALUE}}}.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise InputError(f"argument '{item}' is not KEY=VALUE")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        section, dot, name = key.partition(".")
        if sections and dot:
            out.setdefault("changes", {}).setdefault(section, {})[name] = value
        else:
            out[key] = value
    return out


def cmd_ctl(args: argparse.Namespace) -> int:
    check_command(args.command)
    spec = TABLE[args.command]
    cmd_args = parse_kv(args.args, sections=args.command == "configure")
    with client_from(args, client_id=args.client or f"ctl-{os.getpid()}",
                     retries=args.retries) as client:
        try:  # a timeout given is the user's for every command, a slow one's too
            reply = client.request(args.command, cmd_args, args.timeout)
        except CommandTimeout as exc:
            print(f"haptic ctl: {exc}; {unheard_words(args, args.cmd)}", file=sys.stderr)
            return NO_REPLY
        if not reply.get("ok"):
            err = reply.get("error") or {}
            print(f"haptic ctl: {args.command}: {err.get('code')}: {err.get('message')}",
                  file=sys.stderr)
            return 1
        print(json.dumps(reply.get("result"), indent=2, default=_json_default))
        if spec.lease and args.command != "release":
            _release_unless_active(client)
    return 0


def _release_unless_active(client: Client) -> None:
    """Give the lease back at once when the finger is not active, so the next controller
    need not wait for it to expire; an active finger keeps it (and stops when it lapses)."""
    with contextlib.suppress(ServiceError):
        if client.call("status").get("state") != "active":
            client.call("release")


def _json_default(obj: Any) -> Any:
    tolist = getattr(obj, "tolist", None)
    return tolist() if tolist is not None else str(obj)


# -- haptic explore ----------------------------------------------------------------------
def register_explore(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Localize the finger (or, for a hand, the object it holds) with a running hapticd, on "
        "one connection: wait for the daemon, "
        "take the lease, activate, start an episode and print each step until it ends, then "
        "stop, turn torque off and release the lease. Exit status: 0 converged, 1 ended "
        "without a pose (the reason is printed), 3 no daemon, 4 the daemon is or went in "
        "fault (torque off; the fault is printed).")
    p.add_argument("--client", metavar="NAME", help="a name for this controller, shown as "
                   "the lease holder (default: explore-PID)")
    p.add_argument("--wait", type=number(0.01, 86_400, "s"), default=60.0, metavar="S",
                   help="seconds to wait for the daemon to answer, read the finger and free "
                        "the lease (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="print only the outcome")
    add_endpoint_options(p)
    p.set_defaults(handler=cmd_explore)


class ExploreFailed(ServiceError):
    """The daemon could not be brought to explore (fault, no reply, lease never free)."""

    def __init__(self, message: str, *, faulted: bool = False) -> None:
        super().__init__(message)
        self.faulted = faulted


def cmd_explore(args: argparse.Namespace) -> int:
    client = client_from(args, client_id=args.client or f"explore-{os.getpid()}")
    sub = subscriber_from(args, ["estimate", "event"])
    with client, sub:
        try:
            started = _start(client, sub, args.wait)
        except ExploreFailed as exc:
            print(f"haptic explore: {exc}", file=sys.stderr)
            if exc.faulted:
                return FAULTED
            return NO_REPLY if isinstance(exc.__cause__, CommandTimeout) else 1
        try:
            return Follower(client, sub, started, quiet=args.quiet).run()
        finally:
            _finish(client)


def _start(client: Client, sub: Subscriber, wait_s: float) -> dict[str, Any]:
    """Bring the daemon from wherever it is to exploring, on this connection's lease."""
    end = time.monotonic() + wait_s
    said: set[str] = set()
    last: Exception | None = None
    while True:
        try:
            status = client.call("status")
            state = status["state"]
            if state == "fault":
                raise ExploreFailed(f"hapticd is in fault: {status['fault']}; clear it with "
                                    "`haptic ctl reset`, then explore again", faulted=True)
            if status.get("configuring"):  # hapticd's own start-up configure, say
                _say(said, "configuring", "waiting: hapticd is configuring")
                last = ExploreFailed("hapticd was still configuring")
            elif state == "unconfigured":
                client.call("configure")
                continue
            elif state == "inactive":
                client.call("activate")
                continue
            else:
                if status["exploring"]:
                    client.call("stop_exploration")  # a controller that left: take over
                result = client.call("start_exploration")
                config = client.call("get_config")
                # the truth comes with our `episode_started`: before it, `sim_truth` is the
                # last episode's (a second explore printed that, 63 mm from the estimate)
                return {**result, "max_steps": config["scenario"]["max_steps"],
                        "object": status.get("object")}
        except CommandFailed as exc:
            if exc.code not in ("lease_held", "bad_state"):
                raise ExploreFailed(str(exc)) from exc
            last = exc
            _say(said, exc.code, f"waiting: {exc}")
        except CommandTimeout as exc:
            last = exc
            _say(said, "timeout", f"waiting for hapticd at {client.endpoint} ...")
        if time.monotonic() > end:
            raise ExploreFailed(f"gave up after {wait_s:g} s: {last}") from last
        sub.recv(0.2)  # a moment for the daemon (a read, a lease expiring); stream skipped


def _say(said: set[str], key: str, text: str) -> None:
    if key not in said:
        said.add(key)
        print(f"haptic explore: {text}", file=sys.stderr, flush=True)


def _finish(client: Client) -> None:
    """Stop exploring, torque off, give the lease back: best effort, briefly, and whole. A
    second signal waits for it (`timeout` sends its SIGTERM to us and to its process group:
    a held-out check's `timeout 20 haptic explore` left the daemon exploring, to its lease's
    expiry, in 2 of 3 runs on servos)."""
    with signals_held():
        for cmd in ("stop_exploration", "deactivate", "release"):
            with contextlib.suppress(CommandFailed, CommandTimeout):
                client.call(cmd, timeout_s=0.5)


class Follower:
    """Prints one episode's steps from the stream while keeping the lease alive."""

    def __init__(self, client: Client, sub: Subscriber, started: dict[str, Any], *,
                 quiet: bool) -> None:
        self.client, self.sub, self.quiet = client, sub, quiet
        self.episode = int(started["episode"])
        self.max_steps = int(started["max_steps"])
        self.truth: list[float] | None = None
        """The simulator's hidden pose, from our `episode_started` (and a hand's steps)."""
        self.hand = started.get("object") is not None
        """A hand holding an object: steps are printed from `step` events."""
        self.step = -1
        self.z = 0.0
        self.estimate: dict[str, Any] | None = None
        self.open_at = time.monotonic() + 2.0
        """Events before our `episode_started` are old news (a stop before we began), unless
        that event never arrives (dropped), when they count again after this time."""
        if not quiet:
            where = (f"the pose of object {started['object']} held by the hand" if self.hand
                     else "from the finger's place")
            print(f"episode {self.episode}: exploring {where} "
                  f"({started['candidates']} hypotheses to start)", flush=True)

    def run(self) -> int:
        next_ping, heard = 0.0, time.monotonic()
        while True:
            now = time.monotonic()
            if now >= next_ping:
                outcome = self._keep_lease()
                if outcome is not None:
                    return outcome
                next_ping = now + PING_S
            if now - heard > 5 * PING_S:
                outcome = self._check_status()  # the stream went quiet: ask directly
                if outcome is not None:
                    return outcome
                heard = now
            msg = self.sub.recv(max(0.0, min(0.2, next_ping - now)))
            if msg is None:
                continue
            heard = time.monotonic()
            if msg.topic == "estimate" and msg["episode"] == self.episode:
                self._on_estimate(msg.body)
            elif msg.topic == "event":
                outcome = self._on_event(msg.body)
                if outcome is not None:
                    return outcome

    def _keep_lease(self) -> int | None:
        try:
            self.client.call("acquire")
        except CommandFailed as exc:
            print(f"haptic explore: lost control: {exc}", file=sys.stderr)
            return 1
        except CommandTimeout as exc:
            print(f"haptic explore: lost contact: {exc}", file=sys.stderr)
            return NO_REPLY
        return None

    def _check_status(self) -> int | None:
        try:
            status = self.client.call("status")
        except (CommandFailed, CommandTimeout):
            return None  # the next lease renewal reports it
        if status["exploring"] or status["estimate"] is None:
            return None
        self._on_estimate(status["estimate"])
        return self._outcome(status["estimate"])

    def _on_estimate(self, est: dict[str, Any]) -> None:
        self.estimate = est
        if est["step"] == self.step or est["step"] == 0 or self.hand:
            return
        self.step = est["step"]
        z = float(est["displacement"][2])
        dz, self.z = z - self.z, z
        if not self.quiet:
            print(f"step {est['step']:3d}  dz {dz * 1e3:+7.3f} mm (z {z * 1e3:+7.3f} mm from "
                  f"the start)  {_belief(est)}", flush=True)

    def _on_event(self, ev: dict[str, Any]) -> int | None:
        name = ev.get("event")
        if name == "episode_started" and ev.get("episode") == self.episode:
            self.open_at = 0.0
            self.truth = ev.get("truth")
        if time.monotonic() < self.open_at:
            return None
        if name == "step" and self.hand and ev.get("episode") == self.episode:
            self.truth = ev.get("truth") or self.truth  # the object moves when turned
            if not self.quiet:
                print(hand_step_text(ev), flush=True)
        if name == "episode_done" and ev.get("episode") == self.episode:
            est = dict(self.estimate or {})
            est.update(converged=ev["converged"], candidates=ev["candidates"], pose=ev["pose"],
                       step=ev["steps"], reason=ev.get("reason"))
            return self._outcome(est)
        if name in ("fault", "stopped", "shutdown"):
            why = ev.get("reason") or ev.get("state")
            said = {"fault": "faulted", "stopped": "stopped", "shutdown": "shut down"}[name]
            print(f"haptic explore: the daemon {said}: {why}", file=sys.stderr)
            return FAULTED if name == "fault" else 1
        return None

    def _outcome(self, est: dict[str, Any]) -> int:
        steps = int(est.get("step", 0))
        axis = "z" if self.hand else "y"
        if self.truth is not None:
            print(f"truth     {pose_text(self.truth, axis)}  (the simulator's)")
        print(f"estimate  {pose_text(est.get('pose'), axis)}  ({_belief(est)})")
        if est.get("reason") == "dropped":
            print(f"result    DROPPED the object at step {steps}: the episode failed; put the "
                  "object back in the hand and configure again")
            return 1
        if est.get("converged"):
            print(f"result    localized in {steps_text(steps)}")
            return 0
        if est.get("reason") == "stuck":
            print(f"result    not localized after {steps_text(steps)}: {NO_SAFE_MOVE}")
            return 1
        why = why_not_converged(candidates=int(est.get("candidates", 0)), steps=steps,
                                max_steps=self.max_steps, pose=est.get("pose"),
                                mode_mass=est.get("mode_mass"), runner_up=est.get("runner_up"),
                                runner_up_mass=est.get("runner_up_mass"), second=axis,
                                where="of the object in the hand" if self.hand
                                else "on this map")
        print(f"result    not localized after {steps_text(steps)}: {why}")
        return 1


def _belief(est: dict[str, Any]) -> str:
    return belief_text(est.get("position_sd"), est.get("heading_sd"), est.get("mode_mass"))
