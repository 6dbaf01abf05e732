"""Loopback by default; CurveZMQ required (and working) for anything else."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import zmq

from service.daemon.config import SecurityConfig
from service.daemon.harness import loopback_config, running_node
from service.errors import ConfigError
from service.wire.client import Client, CommandTimeout
from service.wire.security import check_binds, client_curve_options, generate_keys, is_loopback


@pytest.mark.parametrize("endpoint, local", [
    ("tcp://127.0.0.1:5560", True), ("tcp://127.8.0.1:*", True), ("tcp://localhost:1", True),
    ("tcp://[::1]:5560", True), ("ipc:///tmp/x", True), ("inproc://x", True),
    ("tcp://0.0.0.0:5560", False), ("tcp://*:5560", False), ("tcp://192.168.1.4:1", False),
    ("tcp://eth0:5560", False), ("udp://127.0.0.1:1", False),
    ("tcp://vm:5560", False),  # a host name is exposed, whatever it resolves to now
])
def test_loopback_detection(endpoint: str, local: bool) -> None:
    assert is_loopback(endpoint) is local


def test_exposed_bind_needs_curve() -> None:
    with pytest.raises(ConfigError, match="without CurveZMQ"):
        check_binds(["tcp://127.0.0.1:1", "tcp://*:5561"], SecurityConfig())
    with pytest.raises(ConfigError, match="a host name other than localhost counts as exposed"):
        check_binds(["tcp://vm:5561"], SecurityConfig())
    config = loopback_config()
    exposed = dataclasses.replace(config, endpoints=dataclasses.replace(
        config.endpoints, pub="tcp://0.0.0.0:*"))
    with pytest.raises(ConfigError, match="without CurveZMQ"), running_node(exposed):
        pass


def test_curve_admits_only_authorized_clients(tmp_path: Path) -> None:
    _, server_secret = generate_keys(tmp_path / "server", "server")
    clients = tmp_path / "clients"
    client_public, client_secret = generate_keys(tmp_path / "mine", "lab")
    clients.mkdir()
    (clients / "lab.key").write_bytes(client_public.read_bytes())
    _, stranger_secret = generate_keys(tmp_path / "other", "stranger")
    config = dataclasses.replace(loopback_config(), security=SecurityConfig(
        curve=True, server_secret_key=str(server_secret), authorized_clients=str(clients)))
    server_public = str(tmp_path / "server" / "server.key")
    with running_node(config) as node:
        ok = client_curve_options(server_public, str(client_secret))
        with Client(node.endpoints["cmd"], socket_options=ok, timeout_s=5.0) as c:
            assert c.call("ping") == {"pong": True}
        bad = client_curve_options(server_public, str(stranger_secret))
        with Client(node.endpoints["cmd"], socket_options=bad, timeout_s=0.5,
                    retries=0) as c, pytest.raises(CommandTimeout):
            c.call("ping")
        with Client(node.endpoints["cmd"], timeout_s=0.5, retries=0) as c, \
                pytest.raises(CommandTimeout):
            c.call("ping")  # plain text is refused too
    assert zmq.has("curve")


def test_a_busy_endpoint_is_a_config_error() -> None:
    with running_node(loopback_config()) as node:
        taken = dataclasses.replace(loopback_config(), endpoints=dataclasses.replace(
            loopback_config().endpoints, cmd=node.endpoints["cmd"]))
        with pytest.raises(ConfigError, match="cannot bind"), running_node(taken):
            pass


def test_refused_keys_and_files_that_authorize_nobody_are_logged(tmp_path: Path,
                                                                caplog) -> None:
    """A held-out lab: a stranger's key was refused in silence (the client only times out),
    a junk file and a secret key put in authorized_clients were ignored without a word,
    and a revocation's log line named no key."""
    import logging

    from service.wire.security import KeyRing

    clients = tmp_path / "clients"
    clients.mkdir()
    bob_public, bob_secret = generate_keys(tmp_path / "bob", "bob")
    (clients / "bob.key").write_bytes(bob_public.read_bytes())
    (clients / "junk.key").write_text("not a key\n")
    (clients / "oops.key_secret").write_bytes(bob_secret.read_bytes())
    stranger_public, _ = generate_keys(tmp_path / "stranger", "stranger")
    stranger = zmq.auth.load_certificate(stranger_public)[0]
    with caplog.at_level(logging.WARNING, logger="hapticd.security"):
        ring = KeyRing(clients, min_interval_s=0.0)
        assert not ring.callback("*", stranger) and not ring.callback("*", stranger)
    events = [(r.getMessage(), r.fields) for r in caplog.records]
    ignored = sorted(f["file"] for e, f in events if e == "client_key_ignored")
    assert ignored == ["junk.key", "oops.key_secret"]
    refused = [f for e, f in events if e == "curve_refused"]
    assert len(refused) == 1 and refused[0]["key"] == stranger.decode()  # once, not a flood
    assert ring.callback("*", zmq.auth.load_certificate(bob_public)[0])
    (clients / "bob.key").unlink()
    assert ring.refresh(force=True) and ring.revoked == ("bob.key",)
