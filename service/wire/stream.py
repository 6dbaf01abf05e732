"""The state stream: a ZeroMQ PUB socket, two frames per message `[topic, payload]`.

Each topic (`state`, `estimate`, `cloud`, `event`) has its own sequence number, so a
subscriber to any subset can see gaps. Sends never block: PUB drops messages for a
subscriber whose queue (SNDHWM) is full, so a slow or stuck subscriber costs the loop
nothing. (ZMQ_CONFLATE would keep only the latest message, but it breaks multipart, so
it is not used.) The socket belongs to the thread that created the Publisher.
"""

from __future__ import annotations

from typing import Any

import zmq

from service.wire import envelope as wire
from service.wire.security import bind_server_socket

TOPICS = ("state", "estimate", "cloud", "event")


class Publisher:
    def __init__(self, ctx: zmq.Context, endpoint: str, sndhwm: int = 1000,
                 curve: Any = None) -> None:
        self._sock, self.endpoint = bind_server_socket(
            ctx, zmq.PUB, endpoint, {zmq.SNDHWM: sndhwm, zmq.LINGER: 200}, curve)
        self.seq = dict.fromkeys(TOPICS, 0)
        self.sent = dict.fromkeys(TOPICS, 0)
        self.dropped = 0
        self.unbound = False
        """Between `rebind`'s unbind and its bind (the messages go to nobody meanwhile)."""
        """Sends refused outright (PUB normally drops silently per subscriber instead)."""

    def publish(self, topic: str, type_: str, fields: dict[str, Any],
                t_mono_ns: int | None = None) -> None:
        if topic not in self.seq:
            raise ValueError(f"unknown topic '{topic}'")
        self.seq[topic] += 1
        payload = wire.encode(type_, self.seq[topic], fields, t_mono_ns=t_mono_ns)
        try:
            self._sock.send_multipart([topic.encode(), payload], flags=zmq.NOBLOCK, copy=False)
            self.sent[topic] += 1
        except zmq.Again:
            self.dropped += 1

    def event(self, name: str, **fields: Any) -> None:
        """An `event` message: lifecycle changes, faults, accepted commands."""
        self.publish("event", "event", {"event": name, **fields})

    def rebind(self) -> None:
        """Drop every subscriber (unbinding closes their connections) and listen again, so
        each must pass the authenticator anew; sequence numbers carry on. The listener
        closes asynchronously: `ensure_bound` (every tick) binds again once it can."""
        self._sock.unbind(self.endpoint)
        self.unbound = True
        self.ensure_bound()

    def ensure_bound(self) -> None:
        if not self.unbound:
            return
        try:
            self._sock.bind(self.endpoint)
        except zmq.ZMQError:
            return  # the old listener is still closing: next tick
        self.unbound = False

    def close(self) -> None:
        self._sock.close()
