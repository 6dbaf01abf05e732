"""What every client command of hapticd shares (endpoints, CurveZMQ, messages as text), and
the two smallest commands, `haptic watch` and `haptic keygen`.

Imports stay light (pyzmq, msgpack, numpy): `haptic watch` starts in a fraction of a second.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from service.errors import InputError
from service.wire import envelope as wire
from service.wire.client import (
    DEFAULT_ENDPOINTS,
    ENDPOINT_ENV,
    Client,
    Subscriber,
    default_endpoint,
)
from service.wire.stream import TOPICS
from tools.arg_types import integer, number
from tools.signals import interrupted
from tools.words import belief_text, pose_text, quality_text

CURVE_ENV = {"server": "HAPTIC_CURVE_SERVER_KEY", "client": "HAPTIC_CURVE_CLIENT_KEY"}


# -- options every client command shares -------------------------------------------------
def add_endpoint_options(p: argparse.ArgumentParser, *, pub: bool = True, cmd: bool = True,
                         cmd_help: str = "command endpoint") -> None:
    """--pub / --cmd with the daemon's defaults (or $HAPTIC_PUB / $HAPTIC_CMD), and CURVE."""
    g = p.add_argument_group("connection")
    for kind, wanted, what in (("pub", pub, "stream endpoint"), ("cmd", cmd, cmd_help)):
        if wanted:
            g.add_argument(f"--{kind}", default=default_endpoint(kind), metavar="ENDPOINT",
                           help=f"{what} (default: %(default)s; set ${ENDPOINT_ENV[kind]} to "
                                f"change it; hapticd's own default is "
                                f"{DEFAULT_ENDPOINTS[kind]})")
    g.add_argument("--curve-server-key", metavar="FILE",
                   default=os.environ.get(CURVE_ENV["server"]),
                   help="for a daemon with [security] curve = true: its public key file "
                        f"(NAME.key from `haptic keygen`; default: ${CURVE_ENV['server']})")
    g.add_argument("--curve-client-key", metavar="FILE",
                   default=os.environ.get(CURVE_ENV["client"]),
                   help="with --curve-server-key: this client's secret key file "
                        "(NAME.key_secret; its NAME.key must be in the daemon's "
                        f"authorized_clients directory; default: ${CURVE_ENV['client']})")


def socket_options(args: argparse.Namespace) -> dict[int, Any] | None:
    """CurveZMQ socket options from --curve-server-key / --curve-client-key, if given."""
    server, client = args.curve_server_key, args.curve_client_key
    if not server and not client:
        return None
    if not (server and client):
        raise InputError("CurveZMQ needs both --curve-server-key (the daemon's NAME.key) and "
                         "--curve-client-key (your NAME.key_secret)")
    for path in (server, client):
        if not Path(path).is_file():
            raise InputError(f"key file '{path}' does not exist; `haptic keygen DIR --name "
                             f"NAME` writes a pair")
    from service.wire.security import client_curve_options

    try:
        return client_curve_options(server, client)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the CurveZMQ keys: {exc}") from None


def unheard_words(args: argparse.Namespace, endpoint: str) -> str:
    """Why a daemon may not be heard at `endpoint`, in words: not running there, or - with
    CURVE keys - keys it does not take (a refused handshake is silence, never an error)."""
    words = f"is hapticd running at {endpoint}?"
    if getattr(args, "curve_server_key", None):
        words += (" With CURVE, is --curve-server-key the daemon's NAME.key, and is your "
                  "NAME.key in its authorized_clients folder?")
    return words


def client_from(args: argparse.Namespace, **kwargs: Any) -> Client:
    return Client(args.cmd, socket_options=socket_options(args), **kwargs)


def subscriber_from(args: argparse.Namespace, topics: list[str]) -> Subscriber:
    return Subscriber(args.pub, topics, socket_options=socket_options(args))


def parse_topics(spec: str) -> list[str]:
    topics = [t for t in spec.split(",") if t]
    bad = [t for t in topics if t not in TOPICS]
    if bad or not topics:
        raise InputError(f"--topics: unknown {', '.join(bad) or '(none)'}; topics are "
                         f"{', '.join(TOPICS)}")
    return topics


def deadline(duration: float | None) -> float:
    return float("inf") if duration is None else time.monotonic() + duration


# -- messages as text --------------------------------------------------------------------
def format_message(msg: wire.Message) -> str:
    """One line of text per stream message."""
    b = msg.body
    if msg.topic == "state":
        t = b.get("timing", {})
        return (f"state    #{msg.seq} {b['state']:<9} {fingers_text(b.get('fingers') or [])}"
                f"{' DROPPED' if b.get('dropped') else ''} steps={b['steps_done']} "
                f"{b['phase']} period_p99={t.get('period_p99_ms', 0):.2f} ms "
                f"overruns={t.get('overruns', 0)}")
    if msg.topic == "estimate":
        done = "CONVERGED " if b["converged"] else ""
        hand = b.get("kind") == "hand"
        text = (f"estimate #{msg.seq} episode {b['episode']} step {b['step']}: {done}"
                f"{'object ' if hand else ''}{pose_text(b['pose'], 'z' if hand else 'y')}; "
                f"{belief_text(b['position_sd'], b['heading_sd'], b['mode_mass'])}")
        return f"{text}; {quality_text(b['predicted_quality'], b['quality'])}" if hand else text
    if msg.topic == "cloud":
        return (f"cloud    #{msg.seq} episode {b['episode']} step {b['step']}: "
                f"{len(b['poses'])} hypotheses shown of {b['total']}")
    extra = " ".join(f"{k}={v}" for k, v in b.items() if k != "event")
    return f"event    #{msg.seq} {b.get('event')} {extra}"


def fingers_text(fingers: list[dict[str, Any]]) -> str:
    """Each finger's centre (mm, hand frame) and whether it moves or was blocked."""
    if not fingers:
        return "fingers ?"
    parts = []
    for i, f in enumerate(fingers):
        c = f["centre"]
        flags = "".join(f" {name}" for name in ("moving", "blocked") if f.get(name))
        parts.append(f"{i}: ({c[0] * 1e3:+.2f}, {c[1] * 1e3:+.2f}, {c[2] * 1e3:+.2f}) mm{flags}")
    return ("finger " if len(parts) == 1 else "fingers ") + "; ".join(parts)


# -- haptic watch ------------------------------------------------------------------------
def add_stream_options(p: argparse.ArgumentParser, *, cmd: bool = False) -> None:
    p.add_argument("--topics", default=",".join(TOPICS),
                   help="comma-separated topics (default: %(default)s)")
    p.add_argument("--duration", type=number(0.001, 10**7, "s"), metavar="S",
                   help="stop after S seconds")
    p.add_argument("--count", type=integer(1, 10**9), metavar="N", help="stop after N messages")
    add_endpoint_options(p, cmd=cmd)


def register_watch(p: argparse.ArgumentParser) -> None:
    p.description = ("Print hapticd's stream as text, one line per message, until Ctrl-C, "
                     "--duration or --count (topics: state, estimate, cloud, event; "
                     "docs/protocol.md describes their fields).")
    add_stream_options(p)
    p.add_argument("--state-hz", type=number(0.0, 10_000, "Hz"), default=2.0, metavar="HZ",
                   help="print at most HZ state lines per second, 0 for all (default: "
                        "%(default)s)")
    p.set_defaults(handler=cmd_watch)


def cmd_watch(args: argparse.Namespace) -> int:
    end, n, next_state = deadline(args.duration), 0, 0.0
    with subscriber_from(args, parse_topics(args.topics)) as sub:
        try:
            while (time.monotonic() < end and (args.count is None or n < args.count)
                   and not interrupted()):
                msg = sub.recv(min(0.5, max(0.0, end - time.monotonic())))
                if msg is None:
                    continue
                n += 1
                if msg.topic == "state" and args.state_hz > 0:
                    if time.monotonic() < next_state:
                        continue
                    next_state = time.monotonic() + 1.0 / args.state_hz
                print(format_message(msg), flush=True)
        except KeyboardInterrupt:
            pass  # Ctrl-C is how a watch ends
        gaps = sum(sub.gaps.values())
        if sub.rejected:
            print(f"# {sub.rejected} messages could not be read: {sub.rejection}",
                  file=sys.stderr)
    print(f"# {n} messages, {gaps} missed (sequence gaps)"
          + ("" if n else f"; nothing arrived: {unheard_words(args, args.pub)}"),
          file=sys.stderr)
    return 0


# -- haptic keygen -----------------------------------------------------------------------
def register_keygen(p: argparse.ArgumentParser) -> None:
    p.description = ("Write a CurveZMQ key pair for hapticd or a client: DIRECTORY/NAME.key "
                     "(public: give it to peers) and NAME.key_secret (secret, mode 600). The "
                     "daemon's config names its own .key_secret and a directory of its "
                     "clients' .key files; a client passes --curve-server-key and "
                     "--curve-client-key.")
    p.add_argument("directory", help="folder to write the keys into (created if missing)")
    p.add_argument("--name", default="server", help="file name of the pair (default: "
                                                    "%(default)s)")
    p.set_defaults(handler=cmd_keygen)


def cmd_keygen(args: argparse.Namespace) -> int:
    from service.wire.security import generate_keys

    public, secret = generate_keys(Path(args.directory), args.name)
    print(f"public key (give to peers): {public}\nsecret key (keep private): {secret}")
    return 0
