"""The command channel under abuse: every bad request gets an error reply and changes nothing."""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Iterator

import msgpack
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st

from service.daemon.harness import loopback_config, running_node
from service.daemon.node import Node
from service.errors import ConfigError
from service.wire.client import Client, CommandFailed, Subscriber
from service.wire.commands import TABLE, CommandServer, Deferred, validate
from service.wire.lease import Lease, Peer


@pytest.fixture()
def node() -> Iterator[Node]:
    with running_node(loopback_config({"backend": {"step_duration_s": 0.02}})) as n:
        yield n


@pytest.fixture()
def raw(node: Node) -> Iterator[zmq.Socket]:
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(node.endpoints["cmd"])
    yield sock
    sock.close()
    ctx.term()


def ask(sock: zmq.Socket, *frames: bytes) -> dict:
    sock.send_multipart(list(frames))
    assert sock.poll(5000), "no reply"
    reply = msgpack.unpackb(sock.recv())
    assert reply["v"] == 2 and reply["type"] == "reply"
    return reply


def snapshot(client: Client) -> tuple:
    s = client.status()
    return (s["state"], s["exploring"], s["lease"]["holder"], s["fault"],
            str(client.call("get_config")))


def request(**fields: object) -> bytes:
    return msgpack.packb({"v": 2, "type": "request", "id": 9, **fields})


def test_garbage_gets_error_replies_and_changes_nothing(node: Node, raw: zmq.Socket) -> None:
    with Client(node.endpoints["cmd"]) as ctl:
        ctl.call("activate")
        before = snapshot(ctl)
        cases = [
            (os.urandom(200), "malformed"),
            (b"", "malformed"),
            (msgpack.packb([1, 2]), "malformed"),
            (msgpack.packb({"v": 1, "type": "request", "id": 1, "cmd": "estop"}),
             "bad_version"),
            (request(cmd="format_disk", client="x"), "unknown_command"),
            (request(cmd="reset", args={"force": True}), "bad_args"),
            (request(cmd="start_exploration", args={"repeat": "yes"}), "bad_args"),
            (request(cmd="set_map", args=[1]), "bad_args"),
            (request(cmd="set_map", client="intruder", args={}), "bad_args"),
            (request(cmd="deactivate", client="intruder"), "lease_held"),
            (request(cmd="activate"), "lease_held"),  # another connection holds it
            (request(cmd=7), "malformed"),
            (msgpack.packb({"v": 2, "type": "request", "id": [1], "cmd": "ping"}),
             "malformed"),
            (msgpack.packb({"v": 2, "type": "request", "id": 1, "cmd": "estop",
                            "pad": "x" * 70_000}), "too_large"),
            (b"\x00" * (1 << 20), "too_large"),
            (msgpack.packb(msgpack.ExtType(1, b"\x80\x04")), "malformed"),
            # `cmd` twice: the second ran (activate where a proxy read status)
            (b"\x85\xa1v\x02\xa4type\xa7request\xa2id\x09\xa3cmd\xa6status"
             b"\xa3cmd\xa8activate", "malformed"),
            (msgpack.packb({"v": 2, "type": "request", "id": True, "cmd": "ping"}),
             "malformed"),
        ]
        for payload, code in cases:
            reply = ask(raw, payload)
            assert not reply["ok"] and reply["error"]["code"] == code, (payload[:40], reply)
            assert reply["error"]["message"]
            assert reply["id"] is not True  # `true` is no id: the reply's id is nil
        reply = ask(raw, b"one", b"two")
        assert reply["error"]["code"] == "malformed"
        # each refusal says what to do, not only what is wrong (a held-out lab's client)
        assert "not multipart" in reply["error"]["message"]
        assert "docs/protocol.md" in ask(raw, msgpack.packb([1, 2]))["error"]["message"]
        assert "number each request" in ask(raw, msgpack.packb(
            {"v": 2, "type": "request", "id": [1], "cmd": "ping"}))["error"]["message"]
        assert "ask its holder to release" in ask(raw, request(cmd="activate"))["error"][
            "message"]
        # keys that are wrong leave the id readable: it is echoed (a held-out client)
        reply = ask(raw, msgpack.packb({"v": 2, "type": "request", "id": "ik", "cmd": "ping",
                                        3: 4}))
        assert reply["id"] == "ik" and "keys must be strings" in reply["error"]["message"]
        assert snapshot(ctl) == before
        assert ctl.call("ping") == {"pong": True}  # still serving


def test_out_of_state_requests_are_refused(node: Node) -> None:
    with Client(node.endpoints["cmd"]) as ctl:
        with pytest.raises(CommandFailed) as err:
            ctl.call("start_exploration")
        assert err.value.code == "bad_state" and "activate first" in str(err.value)
        with pytest.raises(CommandFailed, match="bad_state"):
            ctl.call("reset")
        ctl.call("activate")
        with pytest.raises(CommandFailed, match="bad_state"):
            ctl.call("activate")
        with pytest.raises(CommandFailed, match="bad_state"):
            ctl.call("set_map", map="bumps")
        with pytest.raises(CommandFailed, match="bad_config"):
            ctl.call("deactivate") and ctl.call("set_map", map="no-such-map")
        assert ctl.status()["state"] == "inactive"
        assert ctl.call("get_config")["scenario"]["map"] == "peaks"


def test_a_refused_set_map_leaves_a_free_lease_free(node: Node, tmp_path) -> None:
    """A client written from the docs alone found that a `set_map` refused only when the
    compute process failed to load the file took the free lease (and kept it)."""
    with Client(node.endpoints["cmd"]) as ctl:
        with pytest.raises(CommandFailed, match="bad_config"):
            ctl.call("set_map", map=str(tmp_path / "nope.npy"))
        status = ctl.status()
        assert status["lease"]["holder"] is None and status["state"] == "inactive"
        assert ctl.call("get_config")["scenario"]["map"] == "peaks"


def test_lease_is_exclusive_and_estop_is_for_everyone(node: Node) -> None:
    with Client(node.endpoints["cmd"]) as a, Client(node.endpoints["cmd"]) as b:
        a.call("activate")
        with pytest.raises(CommandFailed) as err:
            b.call("deactivate")
        assert err.value.code == "lease_held"
        assert b.status()["lease"]["holder"] == a.client_id
        assert b.call("estop", reason="observer saw smoke")["state"] == "fault"
        with Subscriber(node.endpoints["pub"], ["state"]) as sub:
            a.call("reset")
            a.call("release")
            # activation needs a fresh reading after the reset: wait for one to stream
            assert sub.wait_for(lambda m: m["state"] == "inactive", 5.0)
            assert b.call("activate")["state"] == "active"


@pytest.mark.parametrize(("args", "client", "words"), [
    ({"reason": "y" * 4097}, "me", "estop: " + "y" * 4096),
    ({"reason": 3}, "me", "estop: 3"),
    ({"reason": "smoke", "force": True}, "me", "estop: smoke"),
    ([1], "me", "estop: estop"),
    ({"reason": None}, "me", "estop: estop"),
    ({"reason": "smoke"}, "x" * 200, "estop: smoke"),
])
def test_an_estop_is_never_refused_for_its_arguments(node: Node, raw: zmq.Socket, args,
                                                     client, words) -> None:
    """A held-out client's estop with a 4,097-character reason was refused ("must be
    str"), and the finger went on: a stop with odd arguments is still a stop."""
    with Client(node.endpoints["cmd"]) as ctl:
        ctl.call("activate")
        reply = ask(raw, request(cmd="estop", client=client, args=args))
        assert reply["ok"] and reply["result"]["state"] == "fault", reply
        status = ctl.status()
        assert status["fault"] == words and status["state"] == "fault"


def test_a_refused_argument_says_what_it_must_be(node: Node, raw: zmq.Socket) -> None:
    reply = ask(raw, request(cmd="set_map", args={"map": "m" * 4097}))
    assert reply["error"]["message"] == ("'set_map' argument 'map' must be a string of at "
                                         "most 4096 characters")


def test_an_estop_in_fault_keeps_the_first_cause(node: Node) -> None:
    """A fault campaign's finding: an estop while a servo's overheating was latched
    replaced the fault's text, and the servo's diagnosis was gone."""
    with Client(node.endpoints["cmd"]) as a, Client(node.endpoints["cmd"]) as b:
        a.call("estop", reason="servo 2 overheated")
        b.call("estop", reason="operator pressed stop")
        assert b.status()["fault"] == ("estop: servo 2 overheated; then estop: operator "
                                       "pressed stop")
        b.call("estop", reason="operator pressed stop")  # the same again is not news
        assert b.status()["fault"].count("operator pressed stop") == 1


def test_retry_with_same_id_does_not_run_twice(node: Node, raw: zmq.Socket) -> None:
    payload = msgpack.packb({"v": 2, "type": "request", "id": "once", "cmd": "activate",
                             "client": "retrier"})
    first = ask(raw, payload)
    second = ask(raw, payload)
    assert first["ok"] and second == first  # the cached reply, not "cannot activate"


def test_retry_of_a_refused_request_is_refused_again(node: Node, raw: zmq.Socket) -> None:
    """A held-out client's finding: the retry of a request refused for want of the lease ran
    once the lease was free, took it and answered ok; the docs promise the first reply."""
    payload = msgpack.packb({"v": 2, "type": "request", "id": "refused", "cmd": "reset_stats",
                             "client": "retrier"})
    with Client(node.endpoints["cmd"], client_id="holder") as holder:
        holder.call("acquire")
        first = ask(raw, payload)
        holder.call("release")
        second = ask(raw, payload)
        assert holder.status()["lease"]["holder"] is None
    assert first["error"]["code"] == "lease_held" and second == first


@pytest.mark.parametrize(("fields", "code"), [
    ({"cmd": "fly"}, "unknown_command"),
    ({"cmd": "set_map", "args": {"map": 3}}, "bad_args"),
    ({"cmd": "ping", "v": 1}, "bad_version"),
])
def test_a_retried_refusal_of_its_form_is_the_first_reply(node: Node, raw: zmq.Socket,
                                                          fields, code) -> None:
    """A client written from the docs alone: a retry of a request refused for its shape was
    judged again (a new `seq`, and counted again), where the docs promise the first reply."""
    body = {"v": 2, "type": "request", "id": f"again-{code}", "client": "retrier"} | fields
    payload = msgpack.packb(body)
    first = ask(raw, payload)
    errors = node.cmd.errors
    second = ask(raw, payload)
    assert first["error"]["code"] == code and second == first
    assert node.cmd.errors == errors


def test_a_refusal_names_the_command_that_was_sent(node: Node) -> None:
    """set_map while active was refused as "cannot configure while active"."""
    with Client(node.endpoints["cmd"]) as ctl:
        ctl.call("activate")
        with pytest.raises(CommandFailed, match="cannot set_map while active") as refused:
            ctl.call("set_map", map="bumps")
        assert refused.value.code == "bad_state"
        assert ctl.status()["map"] == "peaks"


def test_req_sockets_work_too(node: Node) -> None:
    ctx = zmq.Context()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(node.endpoints["cmd"])
    req.send(request(cmd="ping"))
    assert req.poll(5000)
    assert msgpack.unpackb(req.recv())["result"] == {"pong": True}
    req.close()
    ctx.term()


def test_table_and_validator() -> None:
    assert "ping" in TABLE and not TABLE["estop"].lease and TABLE["activate"].lease
    rid, cmd, client, args, spec = validate({"v": 2, "type": "request", "id": 3,
                                             "cmd": "set_map", "client": "c",
                                             "args": {"map": "peaks", "spacing": None}})
    assert (rid, cmd, args["map"]) == (3, "set_map", "peaks")


def test_lease_expiry_on_a_fake_clock() -> None:
    now = [0]
    lease = Lease(2.0, clock=lambda: now[0])
    a, b = Peer(b"\x00a", fd=7, label="a"), Peer(b"\x00b", fd=8, label="b")
    lease.claim(a)
    now[0] = int(1.5e9)
    lease.touch(a)
    lease.touch(b)  # an observer never renews
    now[0] = int(3.0e9)
    assert lease.expire_due() is None
    now[0] = int(3.6e9)
    assert lease.expire_due() == ("a", "silent") and lease.holder is None
    lease.claim(b)
    assert lease.holder_name == "b"


def test_configure_from_unconfigured() -> None:
    config = dataclasses.replace(loopback_config(), auto_configure=False)
    with running_node(config) as node, Client(node.endpoints["cmd"]) as ctl, \
            Subscriber(node.endpoints["pub"], ["state"]) as sub:
        assert ctl.status()["state"] == "unconfigured"
        with pytest.raises(CommandFailed, match="bad_state"):
            ctl.call("activate")
        with pytest.raises(CommandFailed, match="bad_config"):
            ctl.call("configure", changes={"loop": {"rate_hz": -1}})
        assert ctl.status()["state"] == "unconfigured"
        result = ctl.call("configure", changes={"scenario": {"map": "bumps:20:3", "seed": 4}})
        assert result["state"] == "inactive"
        assert sub.wait_for(lambda m: m["state"] == "inactive" and m["fingers"], 5.0)
        assert ctl.call("get_config")["scenario"]["map"] == "bumps:20:3"


def test_a_backend_fault_latches_until_reset(node: Node) -> None:
    with Client(node.endpoints["cmd"]) as ctl, \
            Subscriber(node.endpoints["pub"], ["event", "state"]) as sub:
        ctl.call("activate")
        ctl.call("start_exploration", repeat=True)
        assert sub.wait_for(lambda m: m.topic == "state" and m["moving"], 5.0)
        node.backend.inject_fault("servo 2 overheated")  # a drill: the sim latches it
        fault = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "fault", 5.0)
        assert fault is not None and "overheated" in fault["reason"]
        state = sub.wait_for(lambda m: m.topic == "state", 5.0)
        assert state["state"] == "fault" and not state["torque_on"] and not state["exploring"]
        with pytest.raises(CommandFailed, match="bad_state"):
            ctl.call("activate")
        with pytest.raises(CommandFailed, match="reset, then activate"):
            ctl.call("start_exploration")  # it said "activate first", which is refused
        assert ctl.call("reset")["state"] == "inactive"
        assert sub.wait_for(lambda m: m.topic == "state" and m["state"] == "inactive", 5.0)
        assert ctl.call("activate")["state"] == "active"


class Inert:
    """Controls that record calls and do nothing, for fuzzing the request path alone."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def __getattr__(self, name: str):  # test double only: every control is a no-op
        return lambda *a, **k: self.calls.append(name) or {}


INTS = st.integers(-(2**63), 2**64 - 1)


@settings(max_examples=200, deadline=None)
@given(st.one_of(
    st.binary(max_size=300),
    st.recursive(st.none() | st.booleans() | INTS | st.floats() | st.text(max_size=20)
                 | st.binary(max_size=20),
                 lambda inner: st.lists(inner, max_size=4)
                 | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                 max_leaves=20).map(lambda v: msgpack.packb(v)),
    st.dictionaries(st.sampled_from(["v", "type", "id", "cmd", "client", "args"]),
                    st.none() | INTS | st.text(max_size=12)
                    | st.dictionaries(st.text(max_size=8), INTS, max_size=3),
                    max_size=6).map(lambda v: msgpack.packb(v)),
))
def test_fuzzed_requests_always_get_a_reply(payload: bytes) -> None:
    server = fuzz_server()
    reply = msgpack.unpackb(server.handle(payload))
    assert reply["v"] == 2 and reply["type"] == "reply" and isinstance(reply["ok"], bool)
    if not reply["ok"]:
        assert reply["error"]["code"] in ERROR_CODES


ERROR_CODES = {"malformed", "too_large", "bad_version", "unknown_command", "bad_args",
               "lease_held", "bad_state", "bad_config", "hardware"}  # never "internal"


@functools.cache
def fuzz_server() -> CommandServer:
    """One server for all examples; `handle` alone is exercised, the socket is idle."""
    return CommandServer(zmq.Context.instance(), "inproc://fuzz-commands", Inert(), Lease(1.0))


def test_a_deferred_reply_comes_once_when_settled_and_keeps_the_lease() -> None:
    """Slow work answers later: a retry meanwhile waits for the same reply, and the holder
    waiting for it is not silent (its lease does not run out). Each send is answered once,
    the retry too (a client from the docs alone resent a slow configure and got one reply
    to two sends; a retry after the reply was answered, so one while at work must be)."""
    now = [0]
    deferred = Deferred()

    class SlowControls:
        def configure(self, changes: dict) -> Deferred:
            return deferred

        def on_command(self, cmd: str, client: str | None) -> None:
            pass

    ctx = zmq.Context()
    lease = Lease(1.0, clock=lambda: now[0])
    server = CommandServer(ctx, "tcp://127.0.0.1:*", SlowControls(), lease)
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(server.endpoint)
    try:
        payload = request(cmd="configure", args={"changes": {}})
        for _ in range(2):  # the request, then its retry
            sock.send(payload)
            handled = server.handled
            while server.handled == handled:
                server.poll(100)
            assert not sock.poll(50)  # no reply yet
        assert lease.busy == 1
        now[0] = int(5e9)  # far past ttl_s
        assert lease.expire_due() is None
        deferred.resolve({"state": "inactive"})
        reply = msgpack.unpackb(sock.recv())
        assert reply["ok"] and reply["result"] == {"state": "inactive"} and reply["id"] == 9
        assert msgpack.unpackb(sock.recv()) == reply  # the retry's: the same reply
        assert not sock.poll(50)  # exactly one reply for each of the two sends
        assert lease.busy == 0 and lease.holder is not None  # renewed when answered
        sock.send(payload)  # the same bytes again: the cached reply
        server.poll(1000)
        assert msgpack.unpackb(sock.recv())["seq"] == reply["seq"]
    finally:
        sock.close()
        server.close()
        ctx.term()


def test_a_deferred_refusal_gives_back_the_lease_it_took() -> None:
    """A control command that takes the free lease and is refused only when its slow work
    ends (`set_map` of a file that does not load) leaves the lease free, as a refusal
    found at once does; one from the holder leaves the holder holding."""
    deferred: list[Deferred] = []

    class SlowControls:
        def configure(self, changes: dict) -> Deferred:
            deferred.append(Deferred())
            return deferred[-1]

        def on_command(self, cmd: str, client: str | None) -> None:
            pass

    ctx = zmq.Context()
    lease = Lease(1.0)
    server = CommandServer(ctx, "tcp://127.0.0.1:*", SlowControls(), lease)
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(server.endpoint)

    def send(payload: bytes) -> None:
        sock.send(payload)
        handled = server.handled
        while server.handled == handled:
            server.poll(100)

    try:
        send(request(cmd="configure", args={"changes": {}}))
        assert lease.holder is not None  # taken while the work runs
        deferred[-1].fail(ConfigError("map file 'nope.npy' cannot be used"))
        assert msgpack.unpackb(sock.recv())["error"]["code"] == "bad_config"
        assert lease.holder is None
        send(msgpack.packb({"v": 2, "type": "request", "id": 10, "cmd": "acquire"}))
        assert msgpack.unpackb(sock.recv())["ok"] and lease.holder is not None
        send(msgpack.packb({"v": 2, "type": "request", "id": 11, "cmd": "configure",
                            "args": {"changes": {}}}))
        deferred[-1].fail(ConfigError("map file 'nope.npy' cannot be used"))
        assert not msgpack.unpackb(sock.recv())["ok"]
        assert lease.holder is not None  # it held the lease before: it still does
    finally:
        sock.close()
        server.close()
        ctx.term()


def test_a_fault_names_its_first_cause_and_the_latest_few() -> None:
    """A review's finding: a cause was dropped when an earlier one merely contained it,
    and distinct estops made the text grow without end."""
    from service.daemon.lifecycle import CAUSES, _with_cause

    fault = _with_cause(None, "stop now")
    fault = _with_cause(fault, "stop")
    assert fault == "stop now; then stop"
    for k in range(10):
        fault = _with_cause(fault, f"estop {k}")
    causes = fault.split("; then ")
    assert len(causes) == CAUSES and causes[0] == "stop now" and causes[-1] == "estop 9"


def test_status_right_after_a_torque_command_tells_what_it_did() -> None:
    """A held-out client asked `status` the moment `deactivate` answered and read torque on
    in 4 of 5 tries, though "every command's effect is complete when its reply arrives":
    the state it reported was the loop's last read, from before. A slow loop makes that
    read old every time."""
    config = loopback_config({"loop": {"rate_hz": 10.0}})
    with running_node(config) as node, Client(node.endpoints["cmd"], timeout_s=10) as ctl:
        for _ in range(2):
            ctl.call("activate")
            assert ctl.status()["torque_on"] is True
            ctl.call("deactivate")
            assert ctl.status()["torque_on"] is False


def test_an_estop_during_a_reset_voids_it(node: Node, monkeypatch) -> None:
    """A reset works on the bus beside the loop (`reset_job`): meanwhile requests are
    answered, an estop latches its fault at once, and the reset, done, is refused with the
    daemon still in fault; a reset after it clears the fault."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    with Client(node.endpoints["cmd"], timeout_s=10.0) as ctl, \
            Client(node.endpoints["cmd"], timeout_s=10.0) as other, \
            ThreadPoolExecutor(1) as asker:
        ctl.call("estop", reason="drill")
        release = threading.Event()
        clear = node.backend.clear_fault
        monkeypatch.setattr(node.backend, "clear_fault",
                            lambda: release.wait(10.0) and clear())
        asking = asker.submit(ctl.call, "reset")
        while not other.status()["resetting"]:
            assert not asking.done()
        assert other.call("ping") == {"pong": True}
        assert other.call("estop", reason="again") == {"state": "fault"}
        assert "again" in other.status()["fault"]
        release.set()
        with pytest.raises(CommandFailed) as refused:
            asking.result()
        assert refused.value.code == "bad_state"
        assert "during the reset" in str(refused.value)
        assert ctl.status()["state"] == "fault" and not ctl.status()["resetting"]
        assert ctl.call("reset")["state"] == "inactive"
