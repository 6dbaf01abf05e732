"""The client library: the daemon's stream as Python objects, its commands as calls.

    with Subscriber("tcp://127.0.0.1:5560", ["state", "estimate"]) as sub:
        msg = sub.recv(timeout_s=1.0)          # a service.wire.envelope.Message, or None
        # state: msg["fingers"], one map per finger (protocol version 2; a finger is a
        # hand of one); estimate: msg["kind"] is "finger" or "hand"
    with Controller("tcp://127.0.0.1:5561") as c:   # holds the lease while open
        c.call("activate"); c.call("start_exploration")

`Client` uses one DEALER socket: a request that gets no reply in `timeout_s` is resent with
the same id (the daemon answers a repeat from its cache, so nothing runs twice); after
`retries` resends the socket is rebuilt and CommandTimeout raised. The daemon's lease
belongs to a connection, so control needs one Client for the whole session: a rebuilt
socket is a new connection and has lost the lease. `Controller` keeps it for you.
"""

from __future__ import annotations

import itertools
import os
import random
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any

import msgpack
import zmq

from service.errors import ConfigError, ServiceError
from service.wire import envelope as wire
from service.wire.security import allow_ipv6, port_of
from service.wire.stream import TOPICS

DEFAULT_ENDPOINTS = {"pub": "tcp://127.0.0.1:5560", "cmd": "tcp://127.0.0.1:5561"}
"""hapticd's default stream (PUB) and command (ROUTER) endpoints."""
ENDPOINT_ENV = {"pub": "HAPTIC_PUB", "cmd": "HAPTIC_CMD"}
"""Environment variables that override the defaults, for hapticd and every client."""


def default_endpoint(kind: str) -> str:
    """The endpoint of `kind` ('pub' or 'cmd'): from the environment, else the default."""
    return os.environ.get(ENDPOINT_ENV[kind]) or DEFAULT_ENDPOINTS[kind]


class CommandFailed(ServiceError):
    """The daemon answered with an error; `code` is from docs/protocol.md."""

    def __init__(self, cmd: str, code: str, message: str) -> None:
        super().__init__(f"{cmd}: {code}: {message}")
        self.cmd = cmd
        self.code = code


class CommandTimeout(ServiceError):
    """No reply after all retries: the daemon is down, busy or unreachable."""


def _apply(sock: zmq.Socket, options: dict[int, Any] | None) -> None:
    for opt, value in (options or {}).items():
        sock.setsockopt(opt, value)


def _connect(sock: zmq.Socket, endpoint: str) -> None:
    """Connect, or close the socket and say what is wrong with the endpoint."""
    port = port_of(endpoint)
    if port is not None and not port.isdigit():  # tcp://[::1] connected somewhere and waited
        sock.close(linger=0)
        raise ConfigError(f"cannot connect to '{endpoint}': it names no port; an endpoint "
                          "looks like tcp://127.0.0.1:5561, tcp://[::1]:5561 or ipc:///path")
    try:
        allow_ipv6(sock, endpoint)
        sock.connect(endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise ConfigError(f"cannot connect to '{endpoint}': {exc.strerror}; an endpoint "
                          f"looks like tcp://127.0.0.1:5561 or ipc:///path") from None


class Subscriber:
    """A SUB socket on some topics; tracks sequence gaps per topic."""

    def __init__(self, endpoint: str, topics: Iterable[str] = TOPICS, *,
                 ctx: zmq.Context | None = None, rcvhwm: int = 1000,
                 socket_options: dict[int, Any] | None = None) -> None:
        self._ctx = ctx or zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.RCVHWM, rcvhwm)
        self._sock.setsockopt(zmq.LINGER, 0)
        _apply(self._sock, socket_options)
        for topic in topics:
            if topic not in TOPICS:
                self._sock.close()
                raise ValueError(f"unknown topic '{topic}'; topics: {', '.join(TOPICS)}")
            self._sock.setsockopt(zmq.SUBSCRIBE, topic.encode())
        _connect(self._sock, endpoint)
        self._last: dict[str, int] = {}
        self.gaps: dict[str, int] = dict.fromkeys(TOPICS, 0)
        """Messages missed per topic, from jumps in the sequence numbers."""
        self.received: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self.rejected = 0
        self.rejection: str | None = None
        """Why the last rejected message could not be read (e.g. a daemon of another
        protocol version: its `bad_version` message names both)."""

    def recv_raw(self, timeout_s: float | None = None) -> tuple[str, bytes] | None:
        """The next (topic, payload) without decoding, or None on timeout."""
        ms = -1 if timeout_s is None else max(0, int(timeout_s * 1000))
        if not self._sock.poll(ms):
            return None
        frames = self._sock.recv_multipart()
        if len(frames) != 2:
            self.rejected += 1
            return None
        return frames[0].decode(errors="replace"), frames[1]

    def recv(self, timeout_s: float | None = None) -> wire.Message | None:
        """The next message (None on timeout); undecodable ones are counted and skipped."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            raw = self.recv_raw(left)
            if raw is None:
                if deadline is None or time.monotonic() >= deadline:
                    return None
                continue
            topic, payload = raw
            try:
                msg = wire.decode(payload, topic=topic)
            except wire.WireError as exc:
                self.rejected += 1
                self.rejection = str(exc)
                continue
            self._count(topic, msg.seq)
            return msg

    def _count(self, topic: str, seq: int) -> None:
        if topic not in self.received:
            return
        last = self._last.get(topic)
        if last is not None and seq > last + 1:
            self.gaps[topic] += seq - last - 1
        self._last[topic] = seq
        self.received[topic] += 1

    def wait_for(self, predicate: Callable[[wire.Message], bool], timeout_s: float
                 ) -> wire.Message | None:
        """The first message satisfying `predicate` within `timeout_s`, else None."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            msg = self.recv(left)
            if msg is not None and predicate(msg):
                return msg
        return None

    def close(self) -> None:
        self._sock.close(linger=0)

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


SLOW_COMMANDS = frozenset({"configure", "set_map", "set_localizer", "set_policy",
                           "start_exploration"})
"""Commands answered when slow work is done (docs/protocol.md): a map, a localizer, a new
backend. A retry of one waits for the same reply, so waiting long is safe."""


class Client:
    """Commands with ids, timeouts and retries on one connection (which holds the lease, if
    it takes it). `client_id` is only a label the daemon shows; it grants nothing.
    Requests may come from several threads: one runs at a time. SLOW_COMMANDS wait at
    least `slow_timeout_s` unless a call gives its own timeout."""

    def __init__(self, endpoint: str, *, client_id: str | None = None, timeout_s: float = 2.0,
                 retries: int = 2, ctx: zmq.Context | None = None,
                 socket_options: dict[int, Any] | None = None,
                 slow_timeout_s: float = 120.0) -> None:
        self.endpoint = endpoint
        self.client_id = client_id or f"py-{uuid.uuid4().hex[:12]}"
        self.timeout_s = timeout_s
        self.slow_timeout_s = slow_timeout_s
        self.retries = retries
        self._ctx = ctx or zmq.Context.instance()
        self._options = socket_options
        self._ids = itertools.count(random.randrange(1 << 40))  # unique across processes
        self._lock = threading.Lock()
        """One request at a time on the socket (a LeaseKeeper thread shares it)."""
        self._sock = self._connect()

    def _connect(self) -> zmq.Socket:
        sock = self._ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        _apply(sock, self._options)
        _connect(sock, self.endpoint)
        return sock

    def request(self, cmd: str, args: dict[str, Any] | None = None,
                timeout_s: float | None = None) -> dict[str, Any]:
        """The full reply map (ok or not) of one request; CommandTimeout if none came."""
        with self._lock:
            return self._request(cmd, args, timeout_s)

    def _request(self, cmd: str, args: dict[str, Any] | None,
                 timeout_s: float | None) -> dict[str, Any]:
        rid = next(self._ids)
        payload = msgpack.packb({"v": wire.VERSION, "type": "request", "id": rid, "cmd": cmd,
                                 "client": self.client_id, "args": args or {}},
                                use_bin_type=True)
        timeout = self.timeout_s if timeout_s is None else timeout_s
        if timeout_s is None and cmd in SLOW_COMMANDS:
            timeout = max(timeout, self.slow_timeout_s)
        for _attempt in range(self.retries + 1):
            deadline = time.monotonic() + timeout
            if not self._send(payload, timeout):
                continue  # no connection took it in time: a refused handshake, no daemon
            while (left := deadline - time.monotonic()) > 0:
                if not self._sock.poll(max(1, int(left * 1000))):
                    break
                try:
                    reply = wire.unpack_map(self._sock.recv(), max_bytes=wire.MAX_FRAME_BYTES)
                except wire.WireError:
                    continue
                if reply.get("id") == rid:
                    return wire.decode_fields(reply)
        self._sock.close(linger=0)
        self._sock = self._connect()
        raise CommandTimeout(f"no reply to '{cmd}' from {self.endpoint} after "
                             f"{self.retries + 1} tries of {timeout:g} s")

    def _send(self, payload: bytes, timeout: float) -> bool:
        """Send within `timeout`. A DEALER with no connection blocks on send, for ever: a
        CURVE handshake the daemon refused left `call` hanging past its own timeout."""
        if not self._sock.poll(max(1, int(timeout * 1000)), zmq.POLLOUT):
            return False
        try:
            self._sock.send(payload, zmq.NOBLOCK)
        except zmq.Again:
            return False
        return True

    def call(self, cmd: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """The result of a command, or CommandFailed / CommandTimeout."""
        reply = self.request(cmd, args, timeout_s)
        if not reply.get("ok"):
            err = reply.get("error") or {}
            raise CommandFailed(cmd, str(err.get("code")), str(err.get("message")))
        return reply.get("result") or {}

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def close(self) -> None:
        with self._lock:
            self._sock.close(linger=0)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LeaseKeeper:
    """Renew a Client's lease from a background thread, over the client's own connection.

        with Client(cmd) as c, LeaseKeeper(c):
            c.call("activate"); ...   # long waits on the stream no longer lose control

    The lease belongs to the connection that took it, so only that Client can renew it;
    the keeper shares its socket (requests take turns).
    """

    def __init__(self, client: Client, interval_s: float = 1.0) -> None:
        self._client = client
        self.interval_s = interval_s
        self.error: ServiceError | None = None
        """The last renewal that failed (lease taken by another, daemon gone), if any."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lease-keeper", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self._client.call("acquire", timeout_s=max(self.interval_s, 0.5))
                self.error = None
            except (CommandFailed, CommandTimeout) as exc:
                self.error = exc

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5 * self.interval_s + 5)


class Controller(Client):
    """A Client that takes the lease on entering and keeps it until it leaves.

        with Controller(cmd) as c:
            c.call("activate"); c.call("start_exploration")
            ...                                   # the lease is renewed every `keepalive_s`
        # on exit: the lease is released (the finger keeps its state: deactivate first)

    `lease_error` tells whether renewing failed (another connection took over after a
    lapse, or the daemon went away).
    """

    def __init__(self, endpoint: str, *, keepalive_s: float = 1.0, **options: Any) -> None:
        super().__init__(endpoint, **options)
        self._keeper = LeaseKeeper(self, keepalive_s)

    @property
    def lease_error(self) -> ServiceError | None:
        return self._keeper.error

    def __enter__(self) -> Controller:
        try:
            self.call("acquire")
        except BaseException:
            self.close()
            raise
        self._keeper.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._keeper.__exit__()
        try:
            self.call("release", timeout_s=1.0)
        except (CommandFailed, CommandTimeout):
            pass  # the lease is gone already; closing the connection ends it anyway
        finally:
            self.close()
