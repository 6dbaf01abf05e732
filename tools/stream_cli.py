"""`haptic watch / ctl / record / replay / view / keygen`: operator tools for a running hapticd.

    haptic ctl status                       one command; exit 0 ok, 1 error reply, 3 no reply
    haptic ctl set_map map=bumps:20:3       KEY=VALUE arguments (JSON values where they parse)
    haptic ctl start_exploration --follow   keep control and print progress until the episode ends
    haptic watch --topics estimate,event    the stream as text
    haptic record run.hrec --duration 30    the stream to a file; `haptic replay run.hrec` plays it
    haptic view [--png snap.png]            live picture (or a headless snapshot)
    haptic keygen keys --name server        CurveZMQ key pair
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zmq

from service.daemon.config import EndpointConfig
from service.errors import InputError
from service.wire import envelope as wire
from service.wire.client import Client, CommandFailed, CommandTimeout, Subscriber
from service.wire.stream import TOPICS

PUB, CMD = EndpointConfig.pub, EndpointConfig.cmd  # the daemon's defaults
RECORD_FORMAT = "haptic-record"


def register(sub: Any) -> None:
    p = sub.add_parser("watch", help="print the daemon's stream as text")
    _stream_args(p)
    p.add_argument("--state-hz", type=float, default=2.0, help="print at most this many "
                   "state lines per second (0: all)")
    p.set_defaults(handler=cmd_watch)

    p = sub.add_parser("ctl", help="send one command to the daemon (see docs/protocol.md)")
    p.add_argument("command", metavar="COMMAND")
    p.add_argument("args", nargs="*", metavar="KEY=VALUE")
    p.add_argument("--cmd", default=CMD, help=f"command endpoint (default {CMD})")
    p.add_argument("--pub", default=PUB, help="stream endpoint, for --follow")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds per try")
    p.add_argument("--retries", type=int, default=2)
    p.add_argument("--client", help="client id (the lease holder's name)")
    p.add_argument("--follow", action="store_true", help="then hold the lease and print "
                   "events until the episode ends; exit 0 if it converged")
    p.set_defaults(handler=cmd_ctl)

    p = sub.add_parser("record", help="record the stream to a file (ends at the daemon's "
                       "shutdown event, --duration, --count or Ctrl-C)")
    p.add_argument("file")
    _stream_args(p)
    p.add_argument("--cmd", default=CMD, help="asked for the config to store with the stream")
    p.set_defaults(handler=cmd_record)

    p = sub.add_parser("replay", help="print or re-publish a recording")
    p.add_argument("file")
    p.add_argument("--publish", metavar="ENDPOINT", help="re-publish on this PUB endpoint")
    p.add_argument("--speed", type=float, default=1.0, help="time scale when publishing")
    p.set_defaults(handler=cmd_replay)

    p = sub.add_parser("view", help="live picture: surface, hypotheses, estimate, path")
    p.add_argument("--pub", default=PUB)
    p.add_argument("--cmd", default=CMD, help="asked for the map to draw")
    p.add_argument("--png", metavar="FILE", help="save one snapshot without a display")
    p.add_argument("--from", dest="source", metavar="RECORDING", help="draw a recording")
    p.add_argument("--duration", type=float, default=3.0,
                   help="with --png: seconds of stream to collect (stops early on convergence)")
    p.add_argument("--map", help="map spec to draw when the daemon cannot be asked")
    p.set_defaults(handler=cmd_view)

    p = sub.add_parser("keygen", help="write a CurveZMQ key pair (NAME.key, NAME.key_secret)")
    p.add_argument("directory")
    p.add_argument("--name", default="server")
    p.set_defaults(handler=cmd_keygen)


def _stream_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pub", default=PUB, help=f"stream endpoint (default {PUB})")
    p.add_argument("--topics", default=",".join(TOPICS), help="comma-separated topics")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--count", type=int, help="stop after this many messages")


def _topics(spec: str) -> list[str]:
    topics = [t for t in spec.split(",") if t]
    bad = [t for t in topics if t not in TOPICS]
    if bad or not topics:
        raise InputError(f"--topics: unknown {', '.join(bad) or '(none)'}; topics are "
                         f"{', '.join(TOPICS)}")
    return topics


def _deadline(duration: float | None) -> float:
    return float("inf") if duration is None else time.monotonic() + duration


def format_message(msg: wire.Message) -> str:
    """One line of text per message."""
    b = msg.body
    if msg.topic == "state":
        c = b.get("centre") or [float("nan")] * 3
        t = b.get("timing", {})
        return (f"state    #{msg.seq} {b['state']:<9} centre=({c[0]:+.4f},{c[1]:+.4f},"
                f"{c[2]:+.4f}) steps={b['steps_done']} {b['phase']} period_p99="
                f"{t.get('period_p99_ms', 0):.2f}ms overruns={t.get('overruns', 0)}")
    if msg.topic == "estimate":
        pose = b["pose"]
        where = "none" if pose is None else (f"x={pose[0]:.4f} y={pose[1]:.4f} "
                                            f"heading={np.degrees(pose[2]):.1f}deg")
        return (f"estimate #{msg.seq} episode={b['episode']} step={b['step']} "
                f"candidates={b['candidates']} {'CONVERGED ' if b['converged'] else ''}{where}")
    if msg.topic == "cloud":
        return f"cloud    #{msg.seq} {len(b['poses'])} of {b['total']} hypotheses"
    extra = " ".join(f"{k}={v}" for k, v in b.items() if k != "event")
    return f"event    #{msg.seq} {b.get('event')} {extra}"


def cmd_watch(args: argparse.Namespace) -> int:
    end, n, next_state = _deadline(args.duration), 0, 0.0
    with Subscriber(args.pub, _topics(args.topics)) as sub:
        while time.monotonic() < end and (args.count is None or n < args.count):
            msg = sub.recv(min(0.5, max(0.0, end - time.monotonic())))
            if msg is None:
                continue
            n += 1
            if msg.topic == "state" and args.state_hz > 0:
                if time.monotonic() < next_state:
                    continue
                next_state = time.monotonic() + 1.0 / args.state_hz
            print(format_message(msg), flush=True)
        gaps = sum(sub.gaps.values())
    print(f"# {n} messages, {gaps} missed (sequence gaps)", file=sys.stderr)
    return 0


def parse_kv(items: list[str]) -> dict[str, Any]:
    """KEY=VALUE pairs; VALUE is JSON when it parses (numbers, true, {...}), else a string."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise InputError(f"argument '{item}' is not KEY=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def cmd_ctl(args: argparse.Namespace) -> int:
    client = Client(args.cmd, client_id=args.client, timeout_s=args.timeout,
                    retries=args.retries)
    try:
        sub = Subscriber(args.pub, ["estimate", "event"]) if args.follow else None
        try:
            reply = client.request(args.command, parse_kv(args.args))
        except CommandTimeout as exc:
            print(f"haptic ctl: {exc}", file=sys.stderr)
            return 3
        if not reply.get("ok"):
            err = reply.get("error") or {}
            print(f"haptic ctl: {args.command}: {err.get('code')}: {err.get('message')}",
                  file=sys.stderr)
            return 1
        print(json.dumps(reply.get("result"), indent=2, default=_json_default))
        return _follow(client, sub) if sub is not None else 0
    finally:
        client.close()


def _follow(client: Client, sub: Subscriber) -> int:
    """Hold the lease (ping every second) and print progress until the episode ends."""
    with sub:
        next_ping = 0.0
        while True:
            if time.monotonic() >= next_ping:
                try:
                    client.call("acquire")
                except (CommandFailed, CommandTimeout) as exc:
                    print(f"haptic ctl: lost control: {exc}", file=sys.stderr)
                    return 1
                next_ping = time.monotonic() + 1.0
            msg = sub.recv(0.2)
            if msg is None:
                continue
            print(format_message(msg), flush=True)
            if msg.topic == "event" and msg["event"] == "episode_done":
                return 0 if msg["converged"] else 1
            if msg.topic == "event" and msg["event"] in ("fault", "stopped", "shutdown"):
                return 1


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def cmd_record(args: argparse.Namespace) -> int:
    header: dict[str, Any] = {"format": RECORD_FORMAT, "v": wire.VERSION, "config": None}
    try:
        with Client(args.cmd, timeout_s=1.0, retries=0) as c:
            header["config"] = c.call("get_config")
    except (CommandFailed, CommandTimeout):
        pass  # a stream without its config still replays; `view --map` can name the map
    end, n = _deadline(args.duration), 0
    with open(args.file, "wb") as f, Subscriber(args.pub, _topics(args.topics)) as sub:
        f.write(msgpack.packb(header, use_bin_type=True))
        try:
            while time.monotonic() < end and (args.count is None or n < args.count):
                raw = sub.recv_raw(min(0.5, max(0.0, end - time.monotonic())))
                if raw is None:
                    continue
                topic, payload = raw
                f.write(msgpack.packb({"topic": topic, "t_ns": time.monotonic_ns(),
                                       "payload": payload}, use_bin_type=True))
                n += 1
                if topic == "event" and _is_shutdown(payload):
                    break  # the daemon is gone: nothing more will come
        except KeyboardInterrupt:
            pass
    print(f"# recorded {n} messages to {args.file}", file=sys.stderr)
    return 0


def _is_shutdown(payload: bytes) -> bool:
    try:
        return wire.decode(payload).get("event") == "shutdown"
    except wire.WireError:
        return False


def read_recording(path: str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Header and records of a `haptic record` file (strictly decoded, never pickled)."""
    try:
        with open(path, "rb") as f:
            unpacker = msgpack.Unpacker(f, raw=False, strict_map_key=True,
                                        max_buffer_size=64 * 1024 * 1024)
            items = list(unpacker)
    except FileNotFoundError:
        raise InputError(f"recording '{path}' does not exist") from None
    except Exception as exc:
        raise InputError(f"'{path}' is not a haptic recording: {type(exc).__name__}") from None
    if not items or not isinstance(items[0], dict) or items[0].get("format") != RECORD_FORMAT:
        raise InputError(f"'{path}' is not a haptic recording (no header)")
    records = [r for r in items[1:] if isinstance(r, dict) and
               isinstance(r.get("payload"), bytes) and isinstance(r.get("t_ns"), int)]
    return items[0], records


def cmd_replay(args: argparse.Namespace) -> int:
    _, records = read_recording(args.file)
    if args.publish is None:
        for r in records:
            print(format_message(wire.decode(r["payload"], topic=r["topic"])))
        return 0
    from service.daemon.config import SecurityConfig
    from service.wire.security import check_binds

    check_binds([args.publish], SecurityConfig())
    if not args.speed > 0:
        raise InputError("--speed must be > 0")
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    try:
        sock.bind(args.publish)
        print(f"# publishing {len(records)} messages on "
              f"{sock.getsockopt_string(zmq.LAST_ENDPOINT)}", file=sys.stderr)
        start, t0 = time.monotonic_ns(), records[0]["t_ns"] if records else 0
        for r in records:
            due = start + int((r["t_ns"] - t0) / args.speed)
            while (left := due - time.monotonic_ns()) > 0:
                time.sleep(left / 1e9)
            sock.send_multipart([r["topic"].encode(), r["payload"]])
    finally:
        sock.close(linger=500)
        ctx.term()
    return 0


def _surface_for_view(args: argparse.Namespace, config: dict[str, Any] | None):
    from service.episode.scenario import RunSettings, surface_for

    if config is None and args.map is None and args.source is None:
        try:
            with Client(args.cmd, timeout_s=2.0, retries=0) as c:
                config = c.call("get_config")
        except (CommandFailed, CommandTimeout):
            config = None
    scen = (config or {}).get("scenario", {})
    settings = RunSettings(map=args.map or scen.get("map", RunSettings.map),
                           spacing=None if args.map else scen.get("spacing"),
                           radius=scen.get("radius", RunSettings.radius))
    return surface_for(settings)


def cmd_view(args: argparse.Namespace) -> int:
    from tools.viewer import ViewModel, draw, save_png

    view = ViewModel()
    if args.source:
        header, records = read_recording(args.source)
        surface = _surface_for_view(args, header.get("config"))
        for r in records:
            view.update(wire.decode(r["payload"], topic=r["topic"]))
        if not args.png:
            raise InputError("--from needs --png (a recording has no live view)")
        save_png(args.png, surface, view)
        print(f"# wrote {args.png}", file=sys.stderr)
        return 0
    surface = _surface_for_view(args, None)
    with Subscriber(args.pub, ["state", "estimate", "cloud"]) as sub:
        if args.png:
            end = _deadline(args.duration)
            while time.monotonic() < end and not view.converged:
                msg = sub.recv(min(0.2, max(0.0, end - time.monotonic())))
                if msg is not None:
                    view.update(msg)
            save_png(args.png, surface, view)
            print(f"# wrote {args.png}", file=sys.stderr)
            return 0
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 6.5))
        plt.ion()
        while plt.fignum_exists(fig.number):
            end = time.monotonic() + 0.2
            while (left := end - time.monotonic()) > 0:
                msg = sub.recv(left)
                if msg is not None:
                    view.update(msg)
            draw(ax, surface, view)
            plt.pause(0.01)
    return 0


def cmd_keygen(args: argparse.Namespace) -> int:
    from service.wire.security import generate_keys

    public, secret = generate_keys(Path(args.directory), args.name)
    print(f"public key (give to peers): {public}\nsecret key (keep private): {secret}")
    return 0
