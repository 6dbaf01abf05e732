"""The client waits long for the commands the daemon answers when slow work is done, and
only as long as asked for the rest (a daemon that takes its time is simulated)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import msgpack
import pytest
import zmq

from service.wire import envelope as wire
from service.wire.client import SLOW_COMMANDS, Client, CommandTimeout

REPLY_AFTER_S = 0.8
"""How long the simulated daemon takes over every reply."""
FAST_TIMEOUT_S = 0.2


@pytest.fixture()
def slow_daemon() -> Iterator[str]:
    """A ROUTER that answers every request REPLY_AFTER_S after it arrived."""
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.ROUTER)
    sock.setsockopt(zmq.LINGER, 0)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    stop = threading.Event()
    pending: list[tuple[float, list[bytes]]] = []

    def serve() -> None:
        seq = 0
        while not stop.is_set():
            if sock.poll(10):
                peer, payload = sock.recv_multipart()
                pending.append((time.monotonic() + REPLY_AFTER_S, [peer, payload]))
            while pending and pending[0][0] <= time.monotonic():
                _, (peer, payload) = pending.pop(0)
                request = msgpack.unpackb(payload)
                seq += 1
                sock.send_multipart([peer, wire.encode("reply", seq, {
                    "id": request["id"], "ok": True, "result": {"cmd": request["cmd"]}})])
        sock.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield f"tcp://127.0.0.1:{port}"
    stop.set()
    thread.join(5)


def test_a_slow_command_waits_past_the_ordinary_timeout(slow_daemon: str) -> None:
    assert "configure" in SLOW_COMMANDS
    with Client(slow_daemon, timeout_s=FAST_TIMEOUT_S, retries=0, slow_timeout_s=30) as c:
        assert c.call("configure", changes={}) == {"cmd": "configure"}


def test_an_ordinary_command_gives_up_after_its_timeout(slow_daemon: str) -> None:
    with Client(slow_daemon, timeout_s=FAST_TIMEOUT_S, retries=0, slow_timeout_s=30) as c:
        with pytest.raises(CommandTimeout, match="'ping'.*1 tries of 0.2 s"):
            c.call("ping")
        # the late reply to the ping is not taken for the next request's
        assert c.call("set_map", map="peaks") == {"cmd": "set_map"}


def test_a_timeout_given_by_the_call_wins(slow_daemon: str) -> None:
    with (Client(slow_daemon, timeout_s=FAST_TIMEOUT_S, retries=0, slow_timeout_s=30) as c,
          pytest.raises(CommandTimeout, match="'configure'")):
        c.call("configure", timeout_s=FAST_TIMEOUT_S, changes={})


def test_a_call_with_no_connection_to_send_on_times_out_instead_of_hanging() -> None:
    """A DEALER with no connection blocks on send: `make test` once hung for ever in the
    CURVE test, the daemon having refused the stranger's handshake before its first call.
    Here nothing listens and ZMQ_IMMEDIATE keeps a pipe from existing until one does."""
    ctx = zmq.Context()
    probe = ctx.socket(zmq.ROUTER)
    port = probe.bind_to_random_port("tcp://127.0.0.1")
    probe.close(linger=0)  # a port nothing listens on now
    client = Client(f"tcp://127.0.0.1:{port}", ctx=ctx, timeout_s=FAST_TIMEOUT_S, retries=1,
                    socket_options={zmq.IMMEDIATE: 1})
    outcome: list[BaseException] = []

    def call() -> None:
        try:
            client.call("ping")
        except BaseException as exc:  # noqa: BLE001 - the outcome is what is asserted
            outcome.append(exc)

    caller = threading.Thread(target=call, daemon=True)
    caller.start()
    caller.join(20 * FAST_TIMEOUT_S)
    assert not caller.is_alive(), "the call hung past its timeout"  # (its socket stays open)
    assert len(outcome) == 1 and isinstance(outcome[0], CommandTimeout)
    client.close()
    ctx.term()
