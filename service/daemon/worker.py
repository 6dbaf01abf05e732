"""The daemon's compute process: maps, localizer and policy, away from the control loop.

`hapticd`'s loop thread does bus I/O, kinematics, the lease watchdog and the stream; every
piece of slow work (loading and checking a map, building a contact surface, constructing a
localizer, an update with its global checks, a policy's choice) runs here, in a process of
its own (a fresh interpreter, `python -m service.daemon.worker`) at a lower priority, so
the loop keeps its rate whatever the localizer costs, and a localizer that crashes takes
only this process down.

The two talk over a socket pair in the wire format (`service.wire.envelope`: msgpack maps, arrays
as typed bytes, never pickle). Each request carries `req`; each reply echoes it, so the
loop drops answers to requests it has moved past. Requests:

    setup    {req, scenario, settings, backend, cloud_points} -> ready {truth, world} | error
    commit   {req}                  the prepared setup becomes the current one
    discard  {req}                  it is dropped
    start    {req, truth, reading}  -> belief
    update   {req, step, reading}   -> belief; then, while the move is under way, the
                                       localizer's work between steps
    cancel   {req}                  the episode under way is dropped
    exit     {}

`scenario` is `finger` (RunSettings) or `hand` (HandSettings); a `reading` is the whole hand's
(`Explorer._reading`). A belief is {estimate, topic, events, done, command, update_ms,
poses, weights}: the estimate and the rest of the `estimate` topic, the events that
happened (a step, the episode's end), and the next `HandCommand` as one [dx, dy, dz, roll]
or None per finger.

An update runs in slices (the localizers' anytime `work`); between slices the process
looks at the pipe, so a `cancel` (or a new request) cuts a long update short.
"""

from __future__ import annotations

import contextlib
import logging
import os
import traceback
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from service.daemon.json_log import JsonFormatter
from service.errors import InputError
from service.wire import envelope as wire

log = logging.getLogger("hapticd.worker")
NICE = 5
"""The compute process yields the CPU to the control loop when both want it."""


class Worker:
    """The compute process's state and request handlers (also usable in-process, for tests).
    A scenario is a finger's on a map (`finger_compute`) or a hand's holding an object
    (`hand_compute`); both answer the same requests."""

    def __init__(self, send: Any) -> None:
        self._send = send
        self.current: Any = None
        self.candidate: Any = None
        self.cloud_points = 500
        self.episode: Any = None
        self._files: list[Path] = []

    # -- configuration -----------------------------------------------------------------
    def setup(self, req: int, body: dict[str, Any]) -> None:
        from service.daemon import finger_compute, hand_compute

        self._drop_files()  # a previous setup's, never mapped
        fields = dict(body["settings"])
        if fields.get("start") is not None:  # msgpack has no tuples
            fields["start"] = tuple(fields["start"])
        self.cloud_points = int(body.get("cloud_points", 500))
        if body.get("scenario", "finger") == "hand":
            candidate, ready = hand_compute.setup(fields, body["backend"])
        else:
            candidate, ready = finger_compute.setup(fields, body["backend"], self._files)
        self.candidate = candidate
        self._send("ready", req, ready)

    def _drop_files(self) -> None:
        for path in self._files:
            path.unlink(missing_ok=True)  # the loop has mapped them, or never will
        self._files.clear()

    def commit(self, req: int, body: dict[str, Any]) -> None:
        if self.candidate is not None:
            self.current, self.candidate = self.candidate, None
            self.episode = None
        self._drop_files()

    def discard(self, req: int, body: dict[str, Any]) -> None:
        self.candidate = None
        self._drop_files()

    # -- episodes ------------------------------------------------------------------------
    def start(self, req: int, body: dict[str, Any]) -> None:
        self.episode = self._scenario().episode(body.get("truth"), self.cloud_points)
        self._send("belief", req, self.episode.start(body))

    def update(self, req: int, body: dict[str, Any], interrupted: Any) -> None:
        if self.episode is None:
            raise InputError("no episode under way")
        belief = self.episode.update(body, interrupted)
        if belief is None:
            self.episode = None  # cut short: the next request decides what follows
            return
        self._send("belief", req, belief)
        if not belief["done"]:  # the move is under way: the localizer's background share
            self.episode.between_steps(interrupted)

    def cancel(self, req: int, body: dict[str, Any]) -> None:
        self.episode = None

    def _scenario(self) -> Any:
        if self.current is None:
            raise InputError("the compute process has no scenario: configure first")
        return self.current


HANDLERS = ("setup", "commit", "discard", "start", "cancel")


def serve(conn: Connection) -> None:
    """The compute process's main loop (the target of the spawned process)."""
    from threadpoolctl import threadpool_limits

    with contextlib.suppress(OSError):  # (a lower priority is a courtesy, not a must)
        os.nice(NICE)
    threadpool_limits(limits=1)
    seq = [0]

    def send(kind: str, req: int, fields: dict[str, Any]) -> None:
        seq[0] += 1
        try:
            conn.send_bytes(wire.encode(kind, seq[0], {"req": req, **fields}))
        except OSError:  # (BrokenPipeError) the daemon closed its end: it is stopping
            raise _DaemonGone from None

    worker = Worker(send)
    backlog: list[wire.Message] = []

    def interrupted() -> bool:
        """A request arrived: the update under way gives way to it."""
        while conn.poll(0):
            backlog.append(_receive(conn))
        return bool(backlog)

    while True:
        msg = backlog.pop(0) if backlog else _receive(conn)
        if msg is None or msg.type == "exit":
            break
        try:
            _handle(worker, msg, send, interrupted)
        except _DaemonGone:
            break
    worker._drop_files()


class _DaemonGone(Exception):
    """The daemon's end of the socket is closed: nobody is left to answer."""


def _handle(worker: Worker, msg: wire.Message, send: Any, interrupted: Any) -> None:
    """One request; its refusal or failure is a reply (bad_config, internal)."""
    req = int(msg.get("req", 0))
    try:
        if msg.type == "update":
            worker.update(req, msg.body, interrupted)
        elif msg.type in HANDLERS:
            getattr(worker, msg.type)(req, msg.body)
    except _DaemonGone:
        raise
    except InputError as exc:
        send("error", req, {"code": "bad_config", "message": str(exc)})
    except Exception as exc:  # a localizer or policy bug: reported, the process lives on
        log.error("compute process: %s", traceback.format_exc())
        send("error", req, {"code": "internal", "message": f"{type(exc).__name__}: {exc}"})


def _receive(conn: Connection) -> wire.Message | None:
    try:
        return wire.decode(conn.recv_bytes())
    except (EOFError, OSError):
        return None  # the daemon is gone


def main(argv: list[str]) -> int:
    """`python -m service.daemon.worker FD`: serve the daemon on the inherited socket FD."""
    import sys

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter(process="worker"))
    log.addHandler(handler)
    log.propagate = False
    serve(Connection(int(argv[0])))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
