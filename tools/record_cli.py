"""`haptic record`, `haptic replay` and `haptic export`: the daemon's stream kept in a file."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import msgpack

from service.errors import InputError
from service.wire import envelope as wire
from service.wire.client import CommandFailed, CommandTimeout
from tools.stream_cli import (
    add_endpoint_options,
    add_stream_options,
    client_from,
    deadline,
    format_message,
    parse_topics,
    subscriber_from,
)

RECORD_FORMAT = "haptic-record"


def register_record(p: argparse.ArgumentParser) -> None:
    p.description = ("Record hapticd's stream to FILE until the daemon shuts down, "
                     "--duration, --count or Ctrl-C; `haptic replay FILE` plays it back.")
    p.add_argument("file", metavar="FILE")
    add_stream_options(p, cmd=True)
    p.set_defaults(handler=cmd_record)
    p.epilog = "The config is asked for on the --cmd endpoint and stored with the stream."


def cmd_record(args: argparse.Namespace) -> int:
    header: dict[str, Any] = {"format": RECORD_FORMAT, "v": wire.VERSION, "config": None}
    try:
        with client_from(args, timeout_s=1.0, retries=0) as c:
            header["config"] = c.call("get_config")
    except (CommandFailed, CommandTimeout):
        pass  # a stream without its config still replays; `view --map` can name the map
    end, n = deadline(args.duration), 0
    with open(args.file, "wb") as f, subscriber_from(args, parse_topics(args.topics)) as sub:
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


def register_replay(p: argparse.ArgumentParser) -> None:
    p.description = ("Print a recording as text, or re-publish it with its original timing so "
                     "any subscriber (haptic watch, haptic view) sees it as if live.")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--publish", metavar="ENDPOINT",
                   help="re-publish on this PUB endpoint (loopback), e.g. tcp://127.0.0.1:5570")
    p.add_argument("--speed", type=float, default=1.0,
                   help="time scale when publishing (default: %(default)s)")
    p.set_defaults(handler=cmd_replay)


def cmd_replay(args: argparse.Namespace) -> int:
    import zmq

    _, records = read_recording(args.file)
    if args.publish is None:
        for index, r in enumerate(records, 1):
            try:
                line = format_message(wire.decode(r["payload"], topic=str(r.get("topic"))))
            except (wire.WireError, KeyError, TypeError, ValueError, IndexError) as exc:
                raise InputError(f"'{args.file}': message {index} is not a valid "
                                 f"{r.get('topic')!r} message ({type(exc).__name__}: {exc})"
                                 ) from None
            print(line)
        return 0
    from service.wire.security import is_loopback

    if not is_loopback(args.publish):
        raise InputError(f"--publish {args.publish}: replays bind loopback only "
                         f"(tcp://127.0.0.1:PORT or ipc://)")
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


def register_export(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE")
    add_endpoint_options(p, pub=False, cmd=False)
    p.set_defaults(handler=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    raise InputError("haptic export is not written yet")
