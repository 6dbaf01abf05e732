"""A client written only from docs/protocol.md: plain pyzmq and msgpack, no service imports.

The daemon runs in-process here only to get it started; everything below the fixture
talks to it as a foreign program would.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import msgpack
import pytest
import zmq

from service.daemon.harness import loopback_config, running_node


@pytest.fixture()
def endpoints() -> Iterator[dict[str, str]]:
    with running_node(loopback_config({"backend": {"step_duration_s": 0.02}})) as node:
        yield node.endpoints


class Plain:
    """What someone would write from the protocol document."""

    def __init__(self, pub: str, cmd: str) -> None:
        self.ctx = zmq.Context()
        self.cmd = self.ctx.socket(zmq.DEALER)
        self.cmd.connect(cmd)
        self.sub = self.ctx.socket(zmq.SUB)
        for topic in (b"state", b"estimate", b"cloud", b"event"):
            self.sub.setsockopt(zmq.SUBSCRIBE, topic)
        self.sub.connect(pub)
        self.next_id = 0

    def call(self, cmd: str, **args: object) -> dict:
        self.next_id += 1
        self.cmd.send(msgpack.packb({"v": 2, "type": "request", "id": self.next_id,
                                     "cmd": cmd, "client": "plain-client", "args": args}))
        assert self.cmd.poll(5000), "no reply"
        reply = msgpack.unpackb(self.cmd.recv())
        assert reply["type"] == "reply" and reply["id"] == self.next_id
        return reply

    def next(self, topic: bytes, timeout_ms: int = 5000) -> dict:
        while self.sub.poll(timeout_ms):
            got, payload = self.sub.recv_multipart()
            if got == topic:
                return msgpack.unpackb(payload)
        raise AssertionError(f"no {topic!r} message")

    def close(self) -> None:
        self.ctx.destroy(linger=0)


def array(obj: dict) -> list:
    """Decode {dtype, shape, data} for the float32 case, as the document describes."""
    assert obj["dtype"] == "<f4"
    n = 1
    for d in obj["shape"]:
        n *= d
    assert len(obj["data"]) == 4 * n
    return list(struct.unpack(f"<{n}f", obj["data"]))


def test_plain_client_reads_state_and_commands_the_service(endpoints) -> None:
    c = Plain(endpoints["pub"], endpoints["cmd"])
    try:
        state = c.next(b"state")
        for key in ("v", "type", "seq", "t_mono_ns", "t_wall_ns", "state", "fingers", "timing"):
            assert key in state
        assert state["v"] == 2 and state["state"] == "inactive"
        assert len(state["fingers"]) == 1 and len(state["fingers"][0]["centre"]) == 3
        assert state["timing"]["rate_hz"] == 200.0
        later = c.next(b"state")
        assert later["seq"] > state["seq"] and later["t_mono_ns"] > state["t_mono_ns"]

        assert c.call("activate")["result"] == {"state": "active"}
        bad = c.call("teleport")
        assert not bad["ok"] and bad["error"]["code"] == "unknown_command"
        started = c.call("start_exploration")
        assert started["ok"] and started["result"]["episode"] == 1

        cloud = c.next(b"cloud")
        poses = array(cloud["poses"])
        assert cloud["poses"]["shape"][1] == 3 and len(poses) == 3 * cloud["poses"]["shape"][0]
        assert len(array(cloud["weights"])) == cloud["poses"]["shape"][0]

        while True:
            est = c.next(b"estimate", 30000)
            if est["converged"]:
                break
        truth = c.call("status")["result"]["sim_truth"]
        assert est["pose"] == pytest.approx(truth, abs=1e-9)
        assert c.call("deactivate")["result"]["state"] == "inactive"
    finally:
        c.close()


def test_a_subscriber_joining_after_convergence_still_gets_the_estimate(endpoints) -> None:
    first = Plain(endpoints["pub"], endpoints["cmd"])
    try:
        first.call("activate")
        first.call("start_exploration")
        while not first.next(b"estimate", 30000)["converged"]:
            pass
    finally:
        first.close()
    late = Plain(endpoints["pub"], endpoints["cmd"])
    try:
        est = late.next(b"estimate", 5000)
        assert est["converged"] and est["pose"] is not None
    finally:
        late.close()
