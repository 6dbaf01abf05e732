"""The command channel: a ZeroMQ ROUTER answering typed requests from a dispatch table.

A request is `{v, type: "request", id, cmd, client?, args?}`; every request gets exactly
one reply `{v, type: "reply", seq, t_mono_ns, t_wall_ns, id, ok, result | error}`. Names
from the wire are looked up in TABLE, never with getattr, and arguments are checked
against each command's declared fields before anything runs, so a malformed, unknown or
out-of-state request is answered with an error and changes nothing.

Control commands need the lease (`service.wire.lease`), which belongs to the connection
that took it, not to the `client` label a request carries. Anyone may observe (status,
get_config, ping) and anyone may `estop`. With CurveZMQ, a request whose key has been
removed from `authorized_clients` is refused at once. A retried request (the same bytes
on the same connection) gets the cached reply instead of running twice.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import zmq

from firmware_if.errors import FirmwareError, HandConfigError
from service.errors import InputError, StateError
from service.wire import envelope as wire
from service.wire.lease import Lease, LeaseHeld, Peer
from service.wire.security import bind_server_socket

MAX_FRAME_BYTES = wire.MAX_FRAME_BYTES
"""Above this libzmq drops the sender's connection (ZMQ_MAXMSGSIZE) instead of replying."""


class CommandError(Exception):
    """A request refused with a machine-readable code (docs/protocol.md, Errors)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Deferred:
    """A result that comes later: slow work (a configure, an episode's first belief) runs
    off the loop, and the command server replies when the daemon calls `resolve` or `fail`.
    Until then a retry of the same request waits for that reply too, and the lease holder
    waiting for it does not lose the lease for being quiet."""

    def __init__(self, done: Callable[[dict[str, Any] | None, Exception | None], None]
                 | None = None) -> None:
        self._done = done
        """Called once with (result, None) or (None, error); the server sets it."""
        self.settled = False
        self._result: dict[str, Any] | None = None
        self._error: Exception | None = None

    def on_settle(self, done: Callable[[dict[str, Any] | None, Exception | None], None]
                  ) -> Deferred:
        """Call `done(result, error)` once settled (at once if it already is)."""
        self._done = done
        if self.settled:
            done(self._result, self._error)
        return self

    def resolve(self, result: dict[str, Any]) -> None:
        self._settle(result, None)

    def fail(self, error: Exception) -> None:
        self._settle(None, error)

    def _settle(self, result: dict[str, Any] | None, error: Exception | None) -> None:
        if self.settled:
            return
        self.settled = True
        self._result, self._error = result, error
        if self._done is not None:
            self._done(result, error)


class Controls(Protocol):
    """What the command table drives: the daemon's node."""

    def status(self) -> dict[str, Any]: ...
    def config_dict(self) -> dict[str, Any]: ...
    def configure(self, changes: dict[str, Any]) -> dict[str, Any]: ...
    def activate(self) -> dict[str, Any]: ...
    def deactivate(self) -> dict[str, Any]: ...
    def start_exploration(self, repeat: bool) -> dict[str, Any]: ...
    def stop_exploration(self) -> dict[str, Any]: ...
    def reset(self) -> dict[str, Any]: ...
    def estop(self, reason: str) -> dict[str, Any]: ...
    def reset_stats(self) -> dict[str, Any]: ...
    def on_command(self, cmd: str, client: str | None) -> None: ...


MAX_STR = 4096
"""The longest string argument, in characters."""

KINDS: dict[str, Callable[[Any], bool]] = {
    "str": lambda v: isinstance(v, str) and len(v) <= MAX_STR,
    "bool": lambda v: isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "number?": lambda v: v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)),
    "map": lambda v: isinstance(v, dict),
}
KIND_WORDS = {"str": f"a string of at most {MAX_STR} characters", "bool": "true or false",
              "number": "a number", "number?": "a number or nil", "map": "a map"}


def _estop_reason(args: dict[str, Any]) -> str:
    """An estop's reason as given, whatever it is: words cut to `MAX_STR` characters, else
    its repr (an estop is never refused for its arguments)."""
    reason = args.get("reason")
    if reason is None:  # nil is absent, as for every field (it read "estop: None")
        reason = "estop"
    return (reason if isinstance(reason, str) else repr(reason))[:MAX_STR]


@dataclass(frozen=True)
class Command:
    run: Callable[[Controls, dict[str, Any]], dict[str, Any] | Deferred]
    lease: bool
    """Needs (and takes, if free) the controlling lease."""
    fields: dict[str, str]
    """Allowed argument names and their kinds (KINDS); all optional unless in `required`."""
    summary: str
    required: tuple[str, ...] = ()
    refused_for_args: bool = True
    """False for `estop`: a stop asked for with a reason too long, of the wrong type or
    beside an unknown argument still stops (a held-out client's 4,097-character reason
    was refused, and the finger went on)."""


TABLE: dict[str, Command] = {
    "ping": Command(lambda n, a: {"pong": True}, False, {}, "liveness; round-trip timing"),
    "status": Command(lambda n, a: n.status(), False, {}, "lifecycle, exploration, timing"),
    "get_config": Command(lambda n, a: n.config_dict(), False, {}, "the running config"),
    "acquire": Command(lambda n, a: {}, True, {}, "take (or renew) the controlling lease"),
    "release": Command(lambda n, a: {}, True, {}, "give the lease back"),
    "configure": Command(lambda n, a: n.configure(a.get("changes", {})), True,
                         {"changes": "map"}, "apply {section: {key: value}}; open backend"),
    "activate": Command(lambda n, a: n.activate(), True, {}, "torque on"),
    "deactivate": Command(lambda n, a: n.deactivate(), True, {}, "stop, torque off"),
    "start_exploration": Command(lambda n, a: n.start_exploration(a.get("repeat", False)),
                                 True, {"repeat": "bool"}, "localize from here"),
    "stop_exploration": Command(lambda n, a: n.stop_exploration(), True, {},
                                "stop after the current step; torque stays on"),
    "reset": Command(lambda n, a: n.reset(), True, {}, "clear a latched fault"),
    "estop": Command(lambda n, a: n.estop(_estop_reason(a)), False,
                     {"reason": "str"}, "anyone: torque off now, latch a fault",
                     refused_for_args=False),
    "set_map": Command(lambda n, a: n.configure({"scenario": {
        "map": a["map"], "spacing": a.get("spacing")}}, "set_map"), True,
        {"map": "str", "spacing": "number?"}, "change the map", ("map",)),
    "set_localizer": Command(lambda n, a: n.configure({"scenario": {
        "localizer": a["name"], "localizer_options": a.get("options", {})}},
        "set_localizer"), True,
        {"name": "str", "options": "map"}, "change the localizer", ("name",)),
    "set_policy": Command(lambda n, a: n.configure({"scenario": {"policy": a["name"]}},
                                                   "set_policy"), True,
                          {"name": "str"}, "change the exploration policy", ("name",)),
    "reset_stats": Command(lambda n, a: n.reset_stats(), True, {}, "restart timing statistics"),
}


def validate(req: dict[str, Any]) -> tuple[Any, str, str | None, dict[str, Any], Command]:
    """(id, cmd, client, args, Command) of a request, or CommandError naming the problem."""
    try:
        wire.check_envelope(req, need_seq=False)
    except wire.WireError as exc:
        raise CommandError(exc.code, str(exc)) from None
    if req["type"] != "request":
        raise CommandError("malformed", f"expected type 'request', got '{req['type']}'")
    rid = req.get("id")
    if not (isinstance(rid, (int, str)) and not isinstance(rid, bool)):
        raise CommandError("malformed", "request 'id' must be an integer or string (the "
                                        "reply carries it back: number each request)")
    cmd, client, args = req.get("cmd"), req.get("client"), req.get("args", {})
    if not isinstance(cmd, str):
        raise CommandError("malformed", "request 'cmd' must be a string")
    spec = TABLE.get(cmd)
    if spec is None:
        raise CommandError("unknown_command", f"unknown command '{cmd[:64]}'; commands: "
                           f"{', '.join(TABLE)}")
    good_client = client is None or (isinstance(client, str) and 0 < len(client) <= 128)
    if not spec.refused_for_args:
        return (rid, cmd, client if good_client else None,
                args if isinstance(args, dict) else {}, spec)
    if not good_client:
        raise CommandError("bad_args", "'client' must be a string of 1..128 characters")
    if args is None:
        args = {}
    if not isinstance(args, dict):
        raise CommandError("bad_args", "'args' must be a map")
    for name, value in args.items():
        kind = spec.fields.get(name)
        if kind is None:
            raise CommandError("bad_args", f"'{cmd}' takes no argument '{str(name)[:64]}'; "
                               f"it takes: {', '.join(spec.fields) or 'nothing'}")
        if not KINDS[kind](value):
            raise CommandError("bad_args", f"'{cmd}' argument '{name}' must be "
                               f"{KIND_WORDS[kind]}")
    missing = [r for r in spec.required if r not in args]
    if missing:
        raise CommandError("bad_args", f"'{cmd}' needs argument(s) {', '.join(missing)}")
    return rid, cmd, client, args, spec


class CommandServer:
    """Owns the ROUTER socket; `poll` answers whatever requests have arrived."""

    def __init__(self, ctx: zmq.Context, endpoint: str, controls: Controls, lease: Lease, *,
                 max_request_bytes: int = wire.MAX_MESSAGE_BYTES, curve: Any = None) -> None:
        self._sock, self.endpoint = bind_server_socket(
            ctx, zmq.ROUTER, endpoint, {zmq.MAXMSGSIZE: MAX_FRAME_BYTES, zmq.LINGER: 200},
            curve)
        self._monitor = self._sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        # imported by the server only, at its start: zmq's monitor module loads asyncio,
        # 50 ms of every client's start-up otherwise (and of a tick, if done on first use)
        from zmq.utils.monitor import recv_monitor_message

        self._recv_monitor = recv_monitor_message
        self.curve = curve
        self.controls = controls
        self.lease = lease
        self.max_request_bytes = max_request_bytes
        self.seq = 0
        self.handled = 0
        self.errors = 0
        self._recent: OrderedDict[tuple[Any, Any], tuple[bytes, bytes]] = OrderedDict()
        self._pending: dict[tuple[Any, Any], bytes] = {}
        """Requests whose reply a Deferred will give: key -> payload."""
        self._retried: Counter[tuple[Any, Any]] = Counter()
        """Retries of each pending request received while it is at work: each is answered
        when it settles, as a retry after it is (one reply per request sent)."""
        self._controls_accepted = 0
        """Control commands (those that need the lease) accepted so far."""
        self._poller = zmq.Poller()
        self._poller.register(self._sock, zmq.POLLIN)

    def poll(self, timeout_ms: float = 0, max_requests: int = 16) -> int:
        """Answer up to `max_requests` waiting requests, waiting up to `timeout_ms` for one."""
        if timeout_ms > 0 and not self.wait(timeout_ms):
            return 0
        return self.answer(max_requests=max_requests)

    def wait(self, timeout_ms: float) -> bool:
        """Wait up to `timeout_ms` for a request; whether one is waiting."""
        if self._poller.poll(timeout_ms):
            return True
        self._disconnects()
        return False

    def answer(self, until_ns: int | None = None, max_requests: int = 16) -> int:
        """Answer the requests waiting, up to `max_requests`, and none once the monotonic
        clock reads `until_ns`: the rest wait for the loop's next turn."""
        n = 0
        while n < max_requests and (until_ns is None or time.monotonic_ns() < until_ns):
            try:
                frames = self._sock.recv_multipart(flags=zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            n += 1
            self._disconnects()  # a holder that left is gone before its successor is heard
            reply = self._reply_frames(frames)
            if reply is not None:
                with contextlib.suppress(zmq.ZMQError):  # the client went away
                    self._sock.send_multipart(reply, flags=zmq.NOBLOCK)
        self._disconnects()
        return n

    def _disconnects(self) -> None:
        """Closed connections, from the socket monitor: the holder's ends its lease."""
        while True:
            try:
                event = self._recv_monitor(self._monitor, flags=zmq.NOBLOCK)
            except zmq.Again:
                return
            if event["event"] == zmq.EVENT_DISCONNECTED:
                self.lease.disconnected(int(event["value"]))

    def _reply_frames(self, frames: list[zmq.Frame]) -> list[bytes] | None:
        if len(frames) < 2:
            return None
        identity, rest = frames[0].bytes, frames[1:]
        head = [identity]
        if len(rest) >= 2 and len(rest[0]) == 0:  # a REQ client's delimiter
            head, rest = [identity, b""], rest[1:]
        if len(rest) != 1:
            return head + [self._error(None, "malformed", "a request is exactly one frame: "
                                                          "send its msgpack map alone, not "
                                                          "multipart")]
        reply = self.handle(rest[0].bytes, _peer(identity, rest[0]), head)
        return None if reply is None else head + [reply]

    def handle(self, payload: bytes, peer: Peer | None = None,
               head: list[bytes] | None = None) -> bytes | None:
        """One request payload to one reply payload (None: a Deferred will reply later, to
        the connection `head` names); never raises."""
        self.handled += 1
        peer = peer or Peer(b"")
        rid: Any = None
        key: tuple[Any, ...] | None = None
        try:
            try:
                req = wire.unpack_map(payload, self.max_request_bytes)
            except wire.WireError as exc:
                rid = _echoed(exc.request_id)  # a map whose keys are wrong names its request
                raise CommandError(exc.code, str(exc)) from None
            rid = _echoed(req.get("id"))
            if self.curve is not None and not self.curve.authorized(peer.key):
                raise CommandError("unauthorized", "this client's key is no longer in "
                                   "authorized_clients")
            if rid is not None:  # a retry is known by its id: any reply to it is kept
                key = (peer.connection, peer.fd, rid)
                cached = self._recent.get(key)
                if cached is not None and cached[0] == payload:
                    return cached[1]  # the same bytes again: a retry, answered from the cache
                if self._pending.get(key) == payload:
                    self._retried[key] += 1  # a retry of a request still at work: its
                    return None  # reply is coming, once for each time it was sent
            rid, cmd, client, args, spec = validate(req)
            peer = dataclasses.replace(peer, label=client)
            before = self.lease.snapshot()
            if spec.lease:
                try:
                    self.lease.claim(peer)
                except LeaseHeld as exc:
                    raise CommandError("lease_held", str(exc)) from None
            else:
                self.lease.touch(peer)
            try:
                result = spec.run(self.controls, wire.decode_fields(args))
            except Exception:
                self.lease.restore(before)  # a refusal changes nothing
                raise
            if isinstance(result, Deferred):
                self._defer(result, cmd, peer, rid, key, bytes(payload), head,
                            took=before[0] is None and self.lease.holds(peer))
                return None
            # a release of a lease no one held changes nothing: no `command` event
            quiet = cmd == "release" and before[0] is None
            return self._accepted(cmd, peer, rid, key, bytes(payload), result, quiet=quiet)
        except Exception as exc:
            out = self._error(rid, *error_code(exc))
            if key is not None:  # a refusal is answered again as it was, like an acceptance
                self._remember(key, bytes(payload), out)
            return out

    def _accepted(self, cmd: str, peer: Peer, rid: Any, key: tuple[Any, ...], payload: bytes,
                  result: dict[str, Any], *, quiet: bool = False) -> bytes:
        if TABLE[cmd].lease:
            self._controls_accepted += 1
        if cmd == "release":
            self.lease.release()
        if not quiet:
            self.controls.on_command(cmd, peer.name())
        out = self._encode(rid, True, result=result)
        self._remember(key, payload, out)
        return out

    def _remember(self, key: tuple[Any, ...], payload: bytes, out: bytes) -> None:
        """Keep a request's reply, refused or accepted, for its retries (the last 256)."""
        self._recent[key] = (payload, out)
        while len(self._recent) > 256:
            self._recent.popitem(last=False)

    def _defer(self, deferred: Deferred, cmd: str, peer: Peer, rid: Any,
               key: tuple[Any, ...], payload: bytes, head: list[bytes] | None, *,
               took: bool) -> None:
        """Reply when `deferred` settles. `took`: this request took a free lease; refused
        in the end, it gives it back (a refusal changes nothing) unless the holder has had
        another control command accepted meanwhile."""
        self._pending[key] = payload
        holding = self.lease.holds(peer)
        if holding:
            self.lease.busy += 1
        accepted = self._controls_accepted

        def done(result: dict[str, Any] | None, error: Exception | None) -> None:
            self._pending.pop(key, None)
            copies = 1 + self._retried.pop(key, 0)
            if holding:
                self.lease.busy = max(0, self.lease.busy - 1)
                self.lease.touch(peer)
            if (error is not None and took and self.lease.holds(peer) and not self.lease.busy
                    and self._controls_accepted == accepted):
                self.lease.release()
            if error is None:
                out = self._accepted(cmd, peer, rid, key, payload, result)
            else:
                out = self._error(rid, *error_code(error))
                self._remember(key, payload, out)
            if head is not None:
                with contextlib.suppress(zmq.ZMQError):  # the client went away
                    for _ in range(copies):
                        self._sock.send_multipart(head + [out], flags=zmq.NOBLOCK)

        deferred.on_settle(done)

    def _error(self, rid: Any, code: str, message: str) -> bytes:
        self.errors += 1
        return self._encode(rid, False, error={"code": code, "message": message[:1000]})

    def _encode(self, rid: Any, ok: bool, **fields: Any) -> bytes:
        self.seq += 1
        return wire.encode("reply", self.seq, {"id": rid, "ok": ok, **fields})

    def close(self) -> None:
        with contextlib.suppress(zmq.ZMQError):
            self._sock.disable_monitor()
        self._monitor.close(linger=0)
        self._sock.close()


def error_code(exc: Exception) -> tuple[str, str]:
    """(code, message) of the protocol's error for an exception (docs/protocol.md)."""
    if isinstance(exc, CommandError):
        return exc.code, str(exc)
    if isinstance(exc, StateError):
        return "bad_state", str(exc)
    if isinstance(exc, (InputError, HandConfigError)):  # a bad value, map, name or hand file
        return "bad_config", str(exc)
    if isinstance(exc, FirmwareError):
        return "hardware", str(exc)
    code = getattr(exc, "code", None)  # the compute process's own classification
    if code in ("bad_config", "internal"):
        return code, str(exc)
    return "internal", f"{type(exc).__name__}: {exc}"  # a bug must not take the daemon down


def _peer(identity: bytes, frame: zmq.Frame) -> Peer:
    """The connection a request frame came on: routing id, CURVE key, file descriptor."""
    try:
        key = frame.get("User-Id")
    except zmq.ZMQError:  # no ZAP handler: plain loopback
        key = None
    try:
        fd = int(frame.get(zmq.SRCFD))
    except zmq.ZMQError:
        fd = -1
    return Peer(identity, key or None, fd)


def _echoed(rid: Any) -> int | str | None:
    """A request's `id` as its reply echoes it: only an int or a string is one (`true` is
    not)."""
    return rid if isinstance(rid, (int, str)) and not isinstance(rid, bool) else None
