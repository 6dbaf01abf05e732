"""Issue 12, findings 6 and 8: slow work runs off the loop. A big map is built while pings
and estops are answered; the compute process can die without the daemon; a map file's
error tells a client nothing about the file."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.daemon.harness import loopback_config, running_node
from service.wire.client import Client, CommandFailed, Subscriber

BIG_MAP = "peaks:100"
"""1001 x 1001 samples: its surface takes long enough to be seen building (a second)."""


@pytest.fixture()
def node() -> Iterator:
    with running_node(loopback_config({"backend": {"step_duration_s": 0.02}})) as n:
        yield n


def in_background(call) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = call()
        except CommandFailed as exc:
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


def test_set_map_of_a_big_map_never_stops_the_loop_answering(node) -> None:
    cmd = node.endpoints["cmd"]
    with Client(cmd, timeout_s=120.0, retries=0) as ctl, \
            Client(cmd, timeout_s=2.0, retries=0) as other:
        thread, out = in_background(lambda: ctl.call("set_map", map=BIG_MAP))
        answered_while_building = 0
        while thread.is_alive():
            status = other.call("status")  # a CommandTimeout here fails the test
            answered_while_building += status["configuring"]
            other.call("ping")
        thread.join()
        assert out["result"]["state"] == "inactive"
        assert answered_while_building >= 7  # the finding: 6 of 7 pings went unanswered
        assert other.call("get_config")["scenario"]["map"] == BIG_MAP


def test_estop_during_a_configure_is_answered_and_voids_it(node) -> None:
    cmd = node.endpoints["cmd"]
    with Client(cmd, timeout_s=120.0, retries=0) as ctl, \
            Client(cmd, timeout_s=2.0, retries=0) as other:
        before = ctl.call("get_config")
        thread, out = in_background(lambda: ctl.call("set_map", map=BIG_MAP))
        for _ in range(10_000):  # until the configure is under way
            if other.call("status")["configuring"]:
                break
        assert other.call("estop", reason="drill")["state"] == "fault"
        thread.join()
        assert out["error"].code == "bad_state" and "nothing was changed" in str(out["error"])
        assert ctl.call("get_config") == before
        assert ctl.status()["state"] == "fault"
        assert ctl.call("reset")["state"] == "inactive"


def test_a_shutdown_during_a_configure_answers_it() -> None:
    """A held-out client's `configure` got no reply when SIGTERM came while it was under
    way; the protocol promises every request one. It is answered, and nothing changed."""
    with running_node(loopback_config({})) as node, \
            Client(node.endpoints["cmd"], timeout_s=120.0, retries=0) as ctl, \
            Client(node.endpoints["cmd"], timeout_s=2.0, retries=0) as other:
        thread, out = in_background(lambda: ctl.call("set_map", map=BIG_MAP))
        for _ in range(10_000):  # until the configure is under way
            if other.call("status")["configuring"]:
                break
        else:
            pytest.fail("the configure was never seen under way")
        node.stop()  # what the SIGINT, SIGTERM and SIGHUP handlers call
        thread.join(60)
    assert out["error"].code == "bad_state"
    assert "shutting down" in str(out["error"]) and "nothing was changed" in str(out["error"])


def test_a_map_file_error_says_nothing_about_the_file(node, tmp_path: Path) -> None:
    secret = tmp_path / "notes.txt"
    secret.write_text("hunter2 is the password\n")
    with Client(node.endpoints["cmd"], timeout_s=30.0) as ctl:
        messages = []
        for path in (secret, tmp_path / "missing.txt"):
            with pytest.raises(CommandFailed) as err:
                ctl.call("set_map", map=str(path), spacing=0.001)
            assert err.value.code == "bad_config"
            messages.append(str(err.value).replace(str(path), "PATH"))
        assert "hunter2" not in messages[0]
        assert messages[0] == messages[1]  # an existing file and a missing one look alike


def test_a_dead_compute_process_faults_exploration_and_is_replaced(node) -> None:
    with Client(node.endpoints["cmd"], timeout_s=30.0) as ctl, \
            Subscriber(node.endpoints["pub"], ["event"]) as events:
        ctl.call("activate")
        ctl.call("start_exploration", repeat=True)
        node.link.kill()  # as if a localizer had crashed the interpreter
        fault = events.wait_for(lambda m: m["event"] == "fault", 10.0)
        assert fault is not None and "process died" in fault["reason"]
        assert ctl.call("ping") == {"pong": True}
        assert ctl.call("reset")["state"] == "inactive"
        assert ctl.call("configure")["state"] == "inactive"  # on a new compute process
        ctl.call("activate")
        assert ctl.call("start_exploration")["candidates"] > 0
