"""What docs/protocol.md promises a client writer, checked with plain pyzmq + msgpack."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import msgpack
import pytest
import zmq

from service.daemon.harness import loopback_config, running_node
from service.daemon.node import Node
from service.wire.client import Subscriber

_ids = itertools.count(1)


@pytest.fixture()
def node() -> Iterator[Node]:
    config = loopback_config({"backend": {"step_duration_s": 0.05},
                              "lease": {"ttl_s": 0.3, "hold_s": 1.0}})
    with running_node(config) as n:
        yield n


class Raw:
    """A DEALER socket speaking the documented frames, nothing else."""

    def __init__(self, endpoint: str) -> None:
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)

    def send_raw(self, payload: bytes) -> dict:
        self.sock.send(payload)
        assert self.sock.poll(5000), "no reply"
        return msgpack.unpackb(self.sock.recv())

    def req(self, cmd: str, **args) -> dict:
        return self.send_raw(msgpack.packb({"v": 2, "type": "request", "id": next(_ids),
                                            "cmd": cmd, "args": args}))

    def close(self) -> None:
        self.sock.close()


def test_reply_seq_is_one_counter_across_connections(node: Node) -> None:
    a, b = Raw(node.endpoints["cmd"]), Raw(node.endpoints["cmd"])
    seqs = [c.req("ping")["seq"] for c in (a, b, a, b)]
    assert seqs == sorted(seqs) and len(set(seqs)) == 4 and seqs[2] - seqs[0] == 2
    a.close()
    b.close()


def test_id_is_nil_only_when_it_could_not_be_read(node: Node) -> None:
    c = Raw(node.endpoints["cmd"])
    assert c.send_raw(b"\xc1garbage")["id"] is None
    assert c.send_raw(msgpack.packb({"v": 2, "type": "request", "cmd": "ping"}))["id"] is None
    big = msgpack.packb({"v": 2, "type": "request", "id": 5, "cmd": "ping",
                         "args": {"x": "y" * 70_000}})
    reply = c.send_raw(big)
    assert reply["error"]["code"] == "too_large" and reply["id"] is None
    reply = c.send_raw(msgpack.packb({"v": 1, "type": "request", "id": 6, "cmd": "ping"}))
    assert reply["error"]["code"] == "bad_version" and reply["id"] == 6
    c.close()


@pytest.mark.parametrize("cmd, args, code", [
    ("set_map", {"map": 3}, "bad_args"),
    ("configure", {"changes": "x"}, "bad_args"),
    ("set_policy", {}, "bad_args"),
    ("set_map", {"map": "nope.npy"}, "bad_config"),
    ("configure", {"changes": {"scenario": {"seed": -1}}}, "bad_config"),
    ("configure", {"changes": {"nosuch": {}}}, "bad_config"),
])
def test_bad_args_is_the_shape_bad_config_the_values(node: Node, cmd, args, code) -> None:
    c = Raw(node.endpoints["cmd"])
    assert c.req(cmd, **args)["error"]["code"] == code
    c.close()


def _state_after(sub: Subscriber, t_mono_ns: int, timeout_s: float = 5.0):
    return sub.wait_for(lambda m: m.t_mono_ns > t_mono_ns, timeout_s)


def test_a_reset_is_complete_when_a_later_state_shows_the_finger_read(node: Node) -> None:
    c = Raw(node.endpoints["cmd"])
    with Subscriber(node.endpoints["pub"], ["state"]) as sub:
        assert sub.wait_for(lambda m: m["fingers"], 5)
        assert c.req("estop", reason="drill")["result"]["state"] == "fault"
        reply = c.req("reset")
        assert reply["ok"] and reply["result"]["state"] == "inactive"
        ready = sub.wait_for(lambda m: m.t_mono_ns > reply["t_mono_ns"] and
                             m["state"] == "inactive" and m["fingers"]
                             and m["fault"] is None, 5)
        assert ready is not None
    assert c.req("activate")["result"]["state"] == "active"
    c.req("deactivate")
    c.close()


def test_the_holder_returning_during_the_hold(node: Node) -> None:
    first = Raw(node.endpoints["cmd"])
    with Subscriber(node.endpoints["pub"], ["state", "event"]) as sub:
        assert sub.wait_for(lambda m: m.topic == "state" and m["fingers"], 5)
        assert first.req("activate")["ok"] and first.req("start_exploration")["ok"]
        # silent for longer than ttl_s: the lease ends and the finger holds
        assert sub.wait_for(lambda m: m.topic == "event" and m["event"] == "holding", 5)
        back = Raw(node.endpoints["cmd"])
        assert back.req("acquire")["ok"]  # the free lease, on a new connection
        assert back.req("start_exploration")["error"]["code"] == "bad_state"
        assert back.req("stop_exploration")["ok"]  # cancels the hold
        done = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "episode_done", 5)
        assert done is not None and done["reason"] == "stopped"  # the episode is over
        end = time.monotonic() + 1.5  # longer than hold_s: torque stays on
        while time.monotonic() < end:
            back.req("ping")
            time.sleep(0.1)  # renewing the lease at a controller's pace
        status = back.req("status")["result"]
        assert status["state"] == "active" and not status["exploring"]
        assert back.req("start_exploration")["ok"]
        back.req("deactivate")
        back.close()
    first.close()
