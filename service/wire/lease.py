"""Who controls the finger: a lease held by one connection, never by a name.

The daemon's ROUTER socket gives every connection its own routing identity; with CurveZMQ
the ZAP handler also vouches for the peer's public key (the `User-Id` of each message).
The lease belongs to that pair. The `client` string a request may carry is only a label
for logs and the stream: anyone can type it, so it grants nothing. Only requests on the
holder's connection renew the lease (observers never do), it ends on `release`, after
`ttl_s` without a request from the holder, or at once when the holder's connection
closes (the socket monitor reports the file descriptor; a new connection that reuses the
routing identity is still a stranger).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Peer:
    """Who sent a request."""

    routing_id: bytes
    """The ROUTER's identity for the connection."""
    key: str | None = None
    """The peer's CURVE public key (z85) as the ZAP handler reported it, when CURVE is on."""
    fd: int = -1
    """The connection's file descriptor (to match the monitor's disconnect events)."""
    label: str | None = None
    """The self-declared `client` string: shown, never trusted."""

    @property
    def connection(self) -> tuple[bytes, str | None]:
        return (self.routing_id, self.key)

    def name(self) -> str:
        return self.label or "anonymous"


class LeaseHeld(Exception):
    """Another connection holds the lease (the message says for how long)."""


class Lease:
    """One controlling connection at a time, until it goes quiet for `ttl_ns` or leaves."""

    def __init__(self, ttl_s: float, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.ttl_ns = int(ttl_s * 1e9)
        self.holder: Peer | None = None
        self.expires_ns = 0
        self.gone = False
        """The holder's connection closed: the lease ends at the next check."""
        self.busy = 0
        """Requests of the holder still at work (a configure): it is waiting, not silent."""
        self._clock = clock

    @property
    def holder_name(self) -> str | None:
        return None if self.holder is None else self.holder.name()

    def holds(self, peer: Peer) -> bool:
        """Whether `peer` is the holder's own, still open, connection."""
        return (self.holder is not None and not self.gone
                and self.holder.connection == peer.connection and self.holder.fd == peer.fd)

    def claim(self, peer: Peer) -> None:
        """Take the lease if free, renew it if `peer` holds it, else LeaseHeld. A lease that
        ran out is free only once the watchdog has handled its end (within one tick)."""
        now = self._clock()
        if self.holder is not None and not self.holds(peer):
            if self.busy and self.gone:  # its request goes on: no one else's meanwhile
                raise LeaseHeld(f"the lease of '{self.holder.name()}' ends when its slow "
                                f"request (a configure, a reset, ...) has finished; its "
                                f"connection has closed: try again then (estop needs no "
                                f"lease)")
            if self.busy:  # it cannot run out meanwhile (`remaining_s`)
                raise LeaseHeld(f"'{self.holder.name()}' holds the lease on another "
                                f"connection and a slow request of its (a configure, a "
                                f"reset, ...) is still at work; the lease lasts at least "
                                f"{self.ttl_ns / 1e9:.1f} s after that ends (estop needs no "
                                f"lease)")
            if self.gone or now >= self.expires_ns:
                raise LeaseHeld(f"the lease of '{self.holder.name()}' is ending; try again "
                                f"in a moment")
            raise LeaseHeld(f"'{self.holder.name()}' holds the lease on another connection "
                            f"for {(self.expires_ns - now) / 1e9:.1f} s more; the lease "
                            f"belongs to the connection that took it: wait till it ends "
                            f"or ask its holder to release it (estop needs no lease)")
        if self.holder is not None and peer.label is None:  # the holder's label stays
            peer = dataclasses.replace(peer, label=self.holder.label)  # till it gives one
        self.holder = peer
        self.expires_ns = now + self.ttl_ns

    def touch(self, peer: Peer) -> None:
        """A request from the holder's own connection renews the lease; others never do."""
        if self.holds(peer):
            self.expires_ns = self._clock() + self.ttl_ns

    def release(self) -> None:
        self.holder = None
        self.gone = False
        self.busy = 0

    def disconnected(self, fd: int) -> None:
        """The monitor saw connection `fd` close: if it was the holder's, the lease ends."""
        if self.holder is not None and fd >= 0 and self.holder.fd == fd:
            self.gone = True
            self.expires_ns = self._clock()

    def expire_due(self) -> tuple[str, str] | None:
        """(holder's name, why) for a lease that just ended, which is then free; else None.
        Why: 'disconnected' (its connection closed) or 'silent' (nothing for ttl_s)."""
        silent = self._clock() >= self.expires_ns
        # a holder's slow request keeps the lease till it ends, even if its connection
        # closed: else another took the lease while the departed client's configure went
        # on, and took effect under the new holder (a held-out check)
        if self.holder is not None and not self.busy and (self.gone or silent):
            ended = (self.holder.name(), "disconnected" if self.gone else "silent")
            self.release()
            return ended
        return None

    def remaining_s(self) -> float:
        """Seconds before the lease runs out if its holder says nothing; the whole ttl while
        a request of the holder is at work (a configure), which it cannot run out during
        (a helper's client read 0 there and took the lease for lost)."""
        if self.holder is None:
            return 0.0
        if self.busy and not self.gone:
            return self.ttl_ns / 1e9
        return max(0.0, (self.expires_ns - self._clock()) / 1e9)

    def snapshot(self) -> tuple[Peer | None, int, bool]:
        return (self.holder, self.expires_ns, self.gone)

    def restore(self, saved: tuple[Peer | None, int, bool]) -> None:
        """Undo a claim (a refused request changes nothing)."""
        self.holder, self.expires_ns, self.gone = saved
