"""Issue 12, finding 3: the lease belongs to the connection that took it, not to a name."""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import msgpack
import pytest
import zmq

from service.daemon.config import SecurityConfig
from service.daemon.harness import loopback_config, running_node
from service.wire.client import Client, CommandFailed, CommandTimeout, Controller, Subscriber
from service.wire.lease import Lease, Peer
from service.wire.security import client_curve_options, generate_keys


def raw_request(sock: zmq.Socket, cmd: str, client: str, rid: int, **args: object) -> dict:
    sock.send(msgpack.packb({"v": 2, "type": "request", "id": rid, "cmd": cmd,
                             "client": client, "args": args}))
    assert sock.poll(5000), "no reply"
    return msgpack.unpackb(sock.recv())


def test_a_holder_waiting_on_a_slow_request_is_shown_its_whole_lease() -> None:
    now = [0]
    lease = Lease(2.0, clock=lambda: now[0])
    peer = Peer(b"conn", fd=7)
    lease.claim(peer)
    lease.busy += 1  # a configure of the holder's at work
    now[0] = int(5e9)  # past the ttl
    assert lease.expire_due() is None and lease.remaining_s() == 2.0
    lease.busy -= 1
    assert lease.remaining_s() == 0.0 and lease.expire_due() is not None


def test_a_stranger_is_told_the_holders_slow_request_keeps_the_lease() -> None:
    """A held-out C client polled `acquire` while the holder's 23 s `set_map` ran: it was
    told "for 1.0 s more", then "ending; try again in a moment" for 20 s, though the lease
    cannot end while the request works."""
    from service.wire.lease import LeaseHeld

    now = [0]
    lease = Lease(2.0, clock=lambda: now[0])
    lease.claim(Peer(b"conn", fd=7, label="alice"))
    lease.busy += 1
    stranger = Peer(b"other", fd=8)
    for t in (1e9, 5e9):  # within the ttl and past it
        now[0] = int(t)
        with pytest.raises(LeaseHeld, match="still at work; the lease lasts at least 2.0 s"):
            lease.claim(stranger)
    lease.busy -= 1
    with pytest.raises(LeaseHeld, match="is ending"):
        lease.claim(stranger)


def test_a_departed_holders_slow_request_keeps_the_lease_till_it_ends() -> None:
    """A second held-out check: the holder closed its connection during its `set_map`; a
    stranger took the lease at once, and the departed client's map then took effect under
    the stranger's lease."""
    from service.wire.lease import LeaseHeld

    now = [0]
    lease = Lease(2.0, clock=lambda: now[0])
    lease.claim(Peer(b"conn", fd=7, label="alice"))
    lease.busy += 1
    lease.disconnected(7)
    stranger = Peer(b"other", fd=8)
    now[0] = int(5e9)
    assert lease.expire_due() is None
    with pytest.raises(LeaseHeld, match="ends when its slow request .* has finished"):
        lease.claim(stranger)
    lease.busy -= 1  # the request ended
    assert lease.expire_due() == ("alice", "disconnected")
    lease.claim(stranger)
    assert lease.holds(stranger)


def test_the_holders_label_stays_when_its_later_requests_carry_none() -> None:
    """A C client from the docs alone: `activate` labelled "alice", then a request with no
    label on the same connection: `lease_holder` and the later `lease_expired` said
    "anonymous"."""
    lease = Lease(2.0, clock=lambda: 0)
    lease.claim(Peer(b"conn", fd=7, label="alice"))
    lease.claim(Peer(b"conn", fd=7))
    assert lease.holder_name == "alice"
    lease.claim(Peer(b"conn", fd=7, label="alice-2"))  # a label given is the label
    assert lease.holder_name == "alice-2"


@pytest.fixture()
def node():
    config = loopback_config({"backend": {"step_duration_s": 0.05},
                              "lease": {"ttl_s": 0.6, "hold_s": 0.2}})
    with running_node(config) as n:
        yield n


def test_a_stranger_repeating_the_holders_name_controls_nothing(node) -> None:
    ctx = zmq.Context.instance()
    with Client(node.endpoints["cmd"], client_id="lab") as holder, \
            Subscriber(node.endpoints["pub"], ["event"]) as events:
        holder.call("activate")
        holder.call("start_exploration", repeat=True)
        stranger = ctx.socket(zmq.DEALER)
        stranger.setsockopt(zmq.LINGER, 0)
        stranger.connect(node.endpoints["cmd"])
        try:
            for i, cmd in enumerate(("stop_exploration", "deactivate", "set_policy",
                                     "release", "acquire", "reset_stats")):
                args = {"name": "random"} if cmd == "set_policy" else {}
                reply = raw_request(stranger, cmd, "lab", 100 + i, **args)
                assert reply["error"]["code"] == "lease_held", (cmd, reply)
        finally:
            stranger.close()
        status = holder.status()
        assert status["state"] == "active" and status["exploring"]
        assert holder.call("get_config")["scenario"]["policy"] == "info-gain"
        assert events.wait_for(lambda m: m["event"] == "command"
                               and m["cmd"] == "deactivate", 0.3) is None


def test_an_observer_never_keeps_a_silent_controllers_lease(node) -> None:
    with Client(node.endpoints["cmd"], client_id="ctl") as controller, \
            Client(node.endpoints["cmd"], client_id="ctl") as observer, \
            Subscriber(node.endpoints["pub"], ["event"]) as events:
        controller.call("activate")  # then silent, but still connected
        expired = None
        for _ in range(200):  # the observer asks 10 times a second under the same name
            observer.call("status")
            expired = events.wait_for(lambda m: m["event"] == "lease_expired", 0.1)
            if expired is not None:
                break
        assert expired is not None and expired["reason"] == "silent"
        assert events.wait_for(lambda m: m["event"] == "stopped", 5.0) is not None


def test_the_lease_ends_when_its_connection_closes_and_its_identity_is_not_inherited(
        node) -> None:
    ctx = zmq.Context.instance()
    holder = ctx.socket(zmq.DEALER)
    holder.setsockopt(zmq.LINGER, 0)
    holder.setsockopt(zmq.ROUTING_ID, b"controller")
    holder.connect(node.endpoints["cmd"])
    with Subscriber(node.endpoints["pub"], ["event"]) as events, \
            Client(node.endpoints["cmd"]) as observer:
        assert raw_request(holder, "activate", "ctl", 1)["ok"]
        holder.close()
        gone = events.wait_for(lambda m: m["event"] == "lease_expired", 5.0)
        assert gone is not None and gone["reason"] == "disconnected"  # at once, not after ttl
        impostor = ctx.socket(zmq.DEALER)  # same routing identity, a new connection
        impostor.setsockopt(zmq.LINGER, 0)
        impostor.setsockopt(zmq.ROUTING_ID, b"controller")
        impostor.connect(node.endpoints["cmd"])
        try:  # it is any other client: the finger holds, then stops, whatever it asks
            reply = raw_request(impostor, "start_exploration", "ctl", 2)
            assert reply["error"]["code"] == "bad_state", reply
        finally:
            impostor.close()
        assert events.wait_for(lambda m: m["event"] == "stopped", 5.0) is not None
        assert observer.status()["state"] == "inactive"


def test_a_controller_keeps_its_lease_through_repeated_episodes(node) -> None:
    with Controller(node.endpoints["cmd"], keepalive_s=0.1, client_id="long") as ctl, \
            Subscriber(node.endpoints["pub"], ["event"]) as events:
        ctl.call("activate")
        ctl.call("start_exploration", repeat=True)
        done = 0
        deadline = time.monotonic() + 60
        while done < 2 and time.monotonic() < deadline:
            m = events.recv(1.0)
            assert m is None or m["event"] not in ("lease_expired", "stopped", "fault"), m.body
            done += bool(m is not None and m["event"] == "episode_done")
        assert done == 2 and ctl.lease_error is None
        assert ctl.status()["exploring"]  # still going: episodes back to back
        ctl.call("deactivate")
    with Client(node.endpoints["cmd"]) as other:  # released on leaving
        assert other.call("acquire") == {}


def test_curve_keys_own_leases_and_revocation_needs_no_restart(tmp_path: Path) -> None:
    _, server_secret = generate_keys(tmp_path / "server", "server")
    clients = tmp_path / "clients"
    clients.mkdir()
    secrets = {}
    for name in ("lab", "visitor"):
        public, secret = generate_keys(tmp_path / name, name)
        shutil.copy(public, clients / public.name)
        secrets[name] = str(secret)
    config = dataclasses.replace(loopback_config(), security=SecurityConfig(
        curve=True, server_secret_key=str(server_secret), authorized_clients=str(clients)))
    server_public = str(tmp_path / "server" / "server.key")
    with running_node(config) as node:
        opts = {n: client_curve_options(server_public, s) for n, s in secrets.items()}
        with Client(node.endpoints["cmd"], socket_options=opts["lab"], timeout_s=5.0) as lab, \
                Client(node.endpoints["cmd"], socket_options=opts["visitor"],
                       timeout_s=1.0, retries=0) as visitor, \
                Subscriber(node.endpoints["pub"], ["state"],
                           socket_options=opts["visitor"]) as watching:
            lab.call("activate")
            with pytest.raises(CommandFailed) as err:
                visitor.call("deactivate")  # another authorized key is still another holder
            assert err.value.code == "lease_held"
            assert watching.recv(5.0) is not None  # the visitor may observe
            (clients / "visitor.key").unlink()  # revoked, while connected
            deadline = time.monotonic() + 5.0  # the directory is re-read within 0.2 s
            with pytest.raises(CommandFailed) as err:
                while time.monotonic() < deadline:
                    visitor.call("status")
            assert err.value.code == "unauthorized"
            # its subscription is cut (the stream is re-bound) and cannot be re-made
            assert watching.wait_for(lambda m: False, 1.5) is None
            assert watching.recv(1.0) is None
            with Client(node.endpoints["cmd"], socket_options=opts["visitor"], timeout_s=0.5,
                        retries=0) as again, pytest.raises(CommandTimeout):
                again.call("ping")  # a new connection fails the handshake
            assert lab.call("deactivate")["state"] == "inactive"  # the lab is unaffected


def test_the_daemon_answers_on_ipv6_loopback() -> None:
    """A held-out C client's `tcp://[::1]:...` failed "No such device ... is another hapticd
    running there?": ZeroMQ sockets take IPv6 only when asked."""
    import socket

    if not socket.has_ipv6:
        pytest.skip("this machine has no IPv6")
    try:
        probe = socket.socket(socket.AF_INET6)
        probe.bind(("::1", 0))
        probe.close()
    except OSError:
        pytest.skip("this machine has no IPv6 loopback")
    config = loopback_config()
    config = dataclasses.replace(config, endpoints=dataclasses.replace(
        config.endpoints, pub="tcp://[::1]:*", cmd="tcp://[::1]:*"))
    with running_node(config) as node, Controller(node.endpoints["cmd"]) as ctl:
        assert node.endpoints["cmd"].startswith("tcp://[::1]:")
        assert ctl.call("ping") == {"pong": True}


@pytest.mark.parametrize("endpoint", ["tcp://[::1]", "tcp://127.0.0.1", "tcp://[::1]:x"])
def test_an_endpoint_without_a_port_is_named_at_once(endpoint: str) -> None:
    """A held-out check: `haptic ctl --cmd tcp://[::1]` connected somewhere, waited for
    every retry and asked whether hapticd was running (exit 3)."""
    from service.errors import ConfigError

    with pytest.raises(ConfigError, match="it names no port"):
        Controller(endpoint, timeout_s=0.1)


def test_a_release_of_a_free_lease_changes_nothing_and_is_not_announced(node) -> None:
    ctx = zmq.Context.instance()
    stranger = ctx.socket(zmq.DEALER)
    stranger.setsockopt(zmq.LINGER, 0)
    stranger.connect(node.endpoints["cmd"])
    with Subscriber(node.endpoints["pub"], ["event"]) as events, \
            Client(node.endpoints["cmd"], client_id="lab") as holder:
        try:
            assert holder.status()["lease"]["holder"] is None
            reply = raw_request(stranger, "release", "someone", 1)
            assert reply["ok"], reply
        finally:
            stranger.close()
        assert holder.status()["lease"]["holder"] is None
        holder.call("set_policy", name="info-gain")  # announced: the stream's next command
        first = events.wait_for(lambda m: m["event"] == "command", 5.0)
        assert first is not None and first["cmd"] == "set_policy", first
