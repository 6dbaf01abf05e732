"""`haptic record`, `haptic replay` and `haptic export`: the daemon's stream kept in a file.

`record` writes MCAP (tools/recording.py describes the layout); `replay` prints or
re-publishes MCAP and older `.hrec` files; `export` turns a recording's episodes into
`haptic run --json`'s format (or one CSV row per step), from the daemon's `episode_started`,
`step` and `episode_done` events.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import sys
import time
from typing import Any

from service.errors import InputError
from service.wire import envelope as wire
from service.wire.client import CommandFailed, CommandTimeout
from tools.arg_types import number
from tools.outputs import check_outputs
from tools.signals import interrupted, signals_held
from tools.stream_cli import (
    add_stream_options,
    client_from,
    deadline,
    format_message,
    parse_topics,
    subscriber_from,
    unheard_words,
)

DEFAULT_STATE_HZ = 10.0


# -- haptic record -----------------------------------------------------------------------
def register_record(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Record hapticd's stream to FILE (MCAP: one channel per topic, with JSON schemas; "
        "Foxglove Studio and the ROS 2 tools open it) until the daemon shuts down, "
        "--duration, --count, Ctrl-C or SIGTERM. `haptic replay FILE` plays it back, "
        "`haptic export FILE` writes its episodes as JSON or CSV.")
    p.add_argument("file", metavar="FILE.mcap")
    add_stream_options(p, cmd=True)
    p.add_argument("--state-hz", type=number(0.0, 10_000, "Hz"), default=DEFAULT_STATE_HZ,
                   metavar="HZ",
                   help="keep at most HZ `state` messages per second (the daemon sends 200; "
                        "0 keeps all) (default: %(default)s)")
    p.epilog = "The daemon's config is asked for on the --cmd endpoint and stored with it."
    p.set_defaults(handler=cmd_record)


def cmd_record(args: argparse.Namespace) -> int:
    from tools.recording import McapRecorder

    topics = parse_topics(args.topics)
    end, next_state = deadline(args.duration), 0.0
    with subscriber_from(args, topics) as sub, McapRecorder(args.file) as rec:
        try:
            while (time.monotonic() < end and (args.count is None or rec.count < args.count)
                   and not interrupted()):
                msg = sub.recv(min(0.5, max(0.0, end - time.monotonic())))
                if msg is None:
                    continue
                if msg.topic == "state" and args.state_hz > 0:
                    if time.monotonic() < next_state:
                        continue
                    next_state = time.monotonic() + 1.0 / args.state_hz
                with signals_held():
                    rec.write(msg.topic, msg)
                if rec.count == 1:  # the daemon is up: ask for its config now
                    _store_config(args, rec)
                    print(f"# recording to {args.file} (the stream is flowing)",
                          file=sys.stderr, flush=True)
                if msg.topic == "event" and msg.get("event") == "shutdown":
                    break  # the daemon is gone: nothing more will come
        except KeyboardInterrupt:
            pass  # Ctrl-C or SIGTERM: finish the file (its summary and index) below
        gaps = sum(sub.gaps.values())
    print(f"# recorded {rec.count} messages to {args.file} ({gaps} missed)"
          + ("" if rec.count else f"; nothing arrived: {unheard_words(args, args.pub)}"),
          file=sys.stderr)
    return 0


def _store_config(args: argparse.Namespace, rec: Any) -> None:
    try:
        with client_from(args, timeout_s=1.0, retries=1) as c:
            rec.add_config(c.call("get_config"))
    except (CommandFailed, CommandTimeout):
        pass  # a stream without its config still replays and exports


# -- haptic replay -----------------------------------------------------------------------
def register_replay(p: argparse.ArgumentParser) -> None:
    p.description = ("Print a recording (MCAP or an older .hrec) as text, or re-publish it "
                     "with its original timing so any subscriber (haptic watch, haptic view) "
                     "sees it as if live.")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--publish", metavar="ENDPOINT",
                   help="re-publish on this loopback PUB endpoint, e.g. tcp://127.0.0.1:5570")
    p.add_argument("--speed", type=number(0.001, 1000), default=1.0,
                   help="time scale when publishing (default: %(default)s)")
    p.add_argument("--delay", type=number(0.0, 3600, "s"), default=1.0, metavar="S",
                   help="when publishing, wait S seconds after binding so that subscribers "
                        "connect before the first message (default: %(default)s)")
    p.set_defaults(handler=cmd_replay)


def cmd_replay(args: argparse.Namespace) -> int:
    from tools.recording import read_recording, wire_payload

    _, records = read_recording(args.file)
    if not records:
        print(f"# '{args.file}' holds no messages: its recorder heard nothing",
              file=sys.stderr)
    if args.publish is None:
        for index, r in enumerate(records, 1):
            try:
                line = format_message(r.message)
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                raise InputError(f"'{args.file}': message {index} is not a valid "
                                 f"{r.topic!r} message ({type(exc).__name__}: {exc})") from None
            print(line)
        return 0
    import zmq

    from service.wire.security import allow_ipv6, is_loopback

    if not is_loopback(args.publish):
        raise InputError(f"--publish {args.publish}: replays bind loopback only "
                         f"(tcp://127.0.0.1:PORT or ipc://)")
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    try:
        try:
            allow_ipv6(sock, args.publish)
            sock.bind(args.publish)
        except zmq.ZMQError as exc:
            raise InputError(f"cannot bind {args.publish}: {exc}") from None
        print(f"# publishing {len(records)} messages on "
              f"{sock.getsockopt_string(zmq.LAST_ENDPOINT)}", file=sys.stderr)
        time.sleep(max(0.0, args.delay))  # ZeroMQ's slow joiner: let subscribers connect
        start, t0 = time.monotonic_ns(), records[0].t_ns if records else 0
        for r in records:
            due = start + int((r.t_ns - t0) / args.speed)
            while (left := due - time.monotonic_ns()) > 0:
                time.sleep(left / 1e9)
            sock.send_multipart([r.topic.encode(), wire_payload(r.message)])
    finally:
        sock.close(linger=500)
        ctx.term()
    return 0


# -- haptic export -----------------------------------------------------------------------
def register_export(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Write the episodes of a recording (MCAP or .hrec) as `haptic run --json` writes one "
        "(settings, truth, steps, estimate, outcome), or as CSV, one row per step. The "
        "recording needs the `event` topic (the default).")
    p.add_argument("file", metavar="FILE")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--json", metavar="OUT", help="JSON: a list of episodes, or with "
                     "--episode that episode's object; '-' for standard output")
    out.add_argument("--csv", metavar="OUT", help="CSV, one row per step of every episode "
                     "(metres, radians, ms); '-' for standard output")
    p.add_argument("--episode", type=int, metavar="ID",
                   help="only this episode (its id as the daemon numbered it)")
    p.set_defaults(handler=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from tools.recording import read_recording

    target = args.json or args.csv
    check_outputs(target, inputs=(args.file,), stdout=True)
    _, records = read_recording(args.file)
    episodes = episodes_from([r.message for r in records if r.topic == "event"])
    if not episodes:
        raise InputError(f"'{args.file}' holds no episode (no episode_started event; record "
                         f"the event topic while an episode runs)")
    if args.episode is not None:
        if args.episode not in episodes:
            raise InputError(f"no episode {args.episode} in '{args.file}'; it holds "
                             f"{', '.join(map(str, episodes))}")
        episodes = {args.episode: episodes[args.episode]}
    hands = [eid for eid, ep in episodes.items() if (ep["settings"] or {}).get("object")]
    why = ("`haptic export` writes a finger's episodes; a hand's steps are the recording's "
           "`step` events (`haptic replay FILE` prints them)")
    if hands and len(hands) == len(episodes):
        which = (f"episode {hands[0]} in '{args.file}' is a hand's" if len(hands) == 1
                 else f"every episode in '{args.file}' is a hand's")
        raise InputError(f"{which}: {why}")
    if hands:  # a daemon that ran a finger and a hand: the finger's are exported
        print(f"# skipped episode(s) {', '.join(map(str, hands))}: a hand's; {why}",
              file=sys.stderr)
        episodes = {eid: ep for eid, ep in episodes.items() if eid not in hands}
    for eid, ep in episodes.items():
        if not ep.get("complete"):
            print(f"# episode {eid} was still running when the recording ended: exported "
                  f"up to step {len(ep['steps'])}", file=sys.stderr)
    exported = [{k: v for k, v in ep.items() if k != "complete"} for ep in episodes.values()]
    with (contextlib.nullcontext(sys.stdout) if target == "-"
          else open(target, "w", newline="")) as f:
        if args.json:
            json.dump(exported[0] if args.episode is not None else exported, f, indent=1)
            f.write("\n")
        else:
            write_csv(f, episodes)
    if target != "-":
        print(f"# {len(exported)} episode(s) written to {target}", file=sys.stderr)
    return 0


def episodes_from(events: list[wire.Message]) -> dict[int, dict[str, Any]]:
    """{episode id: the episode in `haptic run --json`'s format} from the event stream."""
    episodes: dict[int, dict[str, Any]] = {}
    fault = None  # the last fault's words: an episode it cut ends with them
    for ev in events:
        name, eid = ev.get("event"), ev.get("episode")
        if name == "fault":
            fault = ev.get("reason")
        elif name == "episode_started":
            truth = ev.get("truth")
            episodes[eid] = {
                "settings": ev.get("settings"),
                "truth": None if truth is None else dict(zip(("x", "y", "heading"), truth,
                                                             strict=True)),
                "initial_candidates": ev["candidates"], "steps": [], "complete": False}
        elif eid in episodes and name == "step":
            episodes[eid]["steps"].append({k: v for k, v in ev.body.items()
                                           if k not in ("event", "episode")})
        elif eid in episodes and name == "episode_done":
            episodes[eid].update(_outcome(episodes[eid], ev.body), complete=True,
                                 ended=ev.get("reason"),
                                 fault=fault if ev.get("reason") == "fault" else None)
    for ep in episodes.values():
        if not ep["complete"]:
            ep.update(_outcome(ep, _last_belief(ep)))
    return episodes


def _last_belief(ep: dict[str, Any]) -> dict[str, Any]:
    """An unfinished episode's belief: its last step's."""
    last = ep["steps"][-1] if ep["steps"] else {}
    return {"pose": last.get("estimate"), "candidates": last.get("candidates", 0),
            "converged": False, **{k: last.get(k) for k in ("position_sd", "heading_sd",
                                                              "mode_mass")}}


def _outcome(ep: dict[str, Any], done: dict[str, Any]) -> dict[str, Any]:
    """The estimate and the outcome fields of `haptic run --json` from an episode's end."""
    pose = done.get("pose")
    estimate = None if pose is None else {
        "x": pose[0], "y": pose[1], "heading": pose[2], "candidates": done["candidates"],
        **{k: done.get(k) for k in ("position_sd", "heading_sd", "mode_mass")}}
    out = {"estimate": estimate, "converged": bool(done.get("converged")), "ended": None,
           "fault": None, "interrupted": None, "success": None,
           "wrong_declaration": None, "position_error": None, "heading_error": None,
           "true_pose_eliminated": done.get("true_pose_eliminated")}
    if ep["truth"] is not None and ep["settings"] is not None:
        from service.episode.scenario import Truth, score
        from service.localization.localizers.base import Estimate

        t = ep["truth"]
        s = score(Estimate(pose=None if pose is None else tuple(pose),
                           candidates=done["candidates"], converged=out["converged"]),
                  Truth(t["x"], t["y"], t["heading"]), ep["settings"]["step"])
        out.update(success=s.success, wrong_declaration=s.wrong_declaration,
                   position_error=s.position_error, heading_error=s.heading_error)
    return out


CSV_COLUMNS = ("episode", "index", "move", "command_x_m", "command_y_m", "dx_m", "dy_m",
               "dz_m", "blocked", "candidates", "estimate_x_m", "estimate_y_m",
               "estimate_heading_rad", "position_sd_m", "heading_sd_rad", "mode_mass",
               "compute_ms", "policy_ms", "background_ms", "settle_ms")


def write_csv(f: Any, episodes: dict[int, dict[str, Any]]) -> None:
    out = csv.writer(f)
    out.writerow(CSV_COLUMNS)
    for eid, ep in episodes.items():
        for s in ep["steps"]:
            est = s.get("estimate") or [None] * 3
            out.writerow([eid, s["index"], s["move"], *s["command"], *s["measurement"],
                          s["blocked"], s["candidates"], *est, s.get("position_sd"),
                          s.get("heading_sd"), s.get("mode_mass"), s["compute_ms"],
                          s["policy_ms"], s.get("background_ms"), s.get("settle_ms")])
