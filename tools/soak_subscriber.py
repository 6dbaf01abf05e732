"""One subscriber process of `haptic bench soak`: it reads the daemon's stream as a viewer
would, for a fixed time, then prints what it saw as one JSON line on stdout.

    python -m tools.soak_subscriber MODE ENDPOINT DURATION_S [RECONNECT_S]

MODE is `steady` (one connection throughout; it also times the loop from the `state`
stream while the daemon explores: every tick publishes one, stamped with the tick's start
on the daemon's clock),
`reconnecting` (a new connection every RECONNECT_S seconds) or `stuck` (connected and
subscribed, never reading: its queue fills and the daemon drops for it alone). Gaps are
counted within each connection (a new connection starts a new count).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np
import zmq

from service.wire.client import Subscriber

MODES = ("steady", "reconnecting", "stuck")


def read(endpoint: str, until: float, reconnect_s: float | None) -> dict[str, Any]:
    """Read everything until `until` (monotonic s), reconnecting every `reconnect_s`."""
    ctx = zmq.Context()
    received = gaps = rejected = connections = 0
    periods: list[int] = []
    while time.monotonic() < until:
        sub = Subscriber(endpoint, ctx=ctx)
        connections += 1
        last_seq = last_t = None
        end = until if reconnect_s is None else min(until, time.monotonic() + reconnect_s)
        while time.monotonic() < end:
            msg = sub.recv(min(0.1, max(0.0, end - time.monotonic())))
            if msg is None or msg.topic != "state" or reconnect_s is not None:
                continue
            if last_seq is not None and msg.seq == last_seq + 1 and msg["exploring"]:
                periods.append(msg.t_mono_ns - last_t)  # consecutive ticks, under load
            last_seq, last_t = msg.seq, msg.t_mono_ns
        received += sum(sub.received.values())
        gaps += sum(sub.gaps.values())
        rejected += sub.rejected
        sub.close()
    ctx.term()
    out: dict[str, Any] = {"received": received, "gaps": gaps, "rejected": rejected,
                           "connections": connections}
    if reconnect_s is None:
        ms = np.asarray(periods, dtype=np.float64) / 1e6
        out["periods"] = len(periods)
        if len(periods):
            p50, p99, p999 = np.percentile(ms, [50, 99, 99.9])
            out["period_ms"] = {"p50": float(p50), "p99": float(p99), "p99.9": float(p999),
                                "max": float(ms.max())}
    return out


def stuck(endpoint: str, until: float) -> dict[str, Any]:
    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.connect(endpoint)
    time.sleep(max(0.0, until - time.monotonic()))  # never reads: this is the point
    sock.close(linger=0)
    ctx.term()
    return {"received": 0, "gaps": 0, "rejected": 0, "connections": 1}


def main(argv: list[str]) -> int:
    mode, endpoint, duration = argv[0], argv[1], float(argv[2])
    if mode not in MODES:
        print(f"mode must be one of {', '.join(MODES)}", file=sys.stderr)
        return 2
    until = time.monotonic() + duration
    if mode == "stuck":
        out = stuck(endpoint, until)
    else:
        out = read(endpoint, until, float(argv[3]) if mode == "reconnecting" else None)
    print(json.dumps({"mode": mode, **out}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
