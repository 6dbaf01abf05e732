"""`haptic ctl / watch / record / replay / view / keygen` against an in-process daemon."""

from __future__ import annotations

import argparse
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.daemon.harness import loopback_config, running_node
from service.daemon.node import Node
from service.wire.client import Subscriber
from tools import stream_cli


def run(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="haptic")
    stream_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    return int(args.handler(args) or 0)


@pytest.fixture()
def node() -> Iterator[Node]:
    with running_node(loopback_config({"backend": {"step_duration_s": 0.02}})) as n:
        yield n


def test_ctl_exit_status_reflects_the_reply(node: Node, capsys) -> None:
    cmd = node.endpoints["cmd"]
    assert run("ctl", "status", "--cmd", cmd) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "inactive"
    assert run("ctl", "warp", "--cmd", cmd) == 1
    assert "unknown_command" in capsys.readouterr().err
    assert run("ctl", "set_policy", "name=random", "--cmd", cmd, "--client", "me") == 0
    capsys.readouterr()
    assert run("ctl", "get_config", "--cmd", cmd) == 0
    assert json.loads(capsys.readouterr().out)["scenario"]["policy"] == "random"
    assert run("ctl", "ping", "--cmd", "tcp://127.0.0.1:1", "--timeout", "0.2",
               "--retries", "0") == 3


def test_follow_record_replay_and_view(node: Node, tmp_path: Path, capsys) -> None:
    rec = tmp_path / "run.hrec"
    ep = ["--cmd", node.endpoints["cmd"], "--pub", node.endpoints["pub"]]
    assert run("ctl", "activate", *ep, "--client", "op") == 0
    # Record while an episode runs to convergence under `ctl --follow`.

    recorder = threading.Thread(target=run, args=(
        "record", str(rec), "--pub", node.endpoints["pub"], "--cmd", node.endpoints["cmd"],
        "--topics", "estimate,cloud,event", "--duration", "30"))
    with Subscriber(node.endpoints["pub"], ["state"]) as probe:
        assert probe.recv(5.0) is not None  # the stream is up before recording starts
    recorder.start()
    assert run("ctl", "start_exploration", "--follow", *ep, "--client", "op") == 0
    out = capsys.readouterr().out
    assert "CONVERGED" in out and "episode_done" in out
    assert run("ctl", "deactivate", *ep, "--client", "op") == 0
    node.stop()  # its final shutdown event ends the recording
    recorder.join(40)
    assert not recorder.is_alive()
    assert rec.stat().st_size > 0
    capsys.readouterr()
    assert run("replay", str(rec)) == 0
    assert "CONVERGED" in capsys.readouterr().out
    png = tmp_path / "view.png"
    assert run("view", "--from", str(rec), "--png", str(png)) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_replay_refuses_a_non_recording(tmp_path: Path) -> None:
    bad = tmp_path / "x.hrec"
    bad.write_bytes(b"\x93\x01\x02\x03")
    from service.errors import InputError

    with pytest.raises(InputError, match="not a haptic recording"):
        run("replay", str(bad))


def test_keygen_writes_a_key_pair(tmp_path: Path, capsys) -> None:
    assert run("keygen", str(tmp_path / "keys"), "--name", "lab") == 0
    assert (tmp_path / "keys" / "lab.key").is_file()
    assert (tmp_path / "keys" / "lab.key_secret").stat().st_mode & 0o077 == 0


def test_view_png_from_a_live_daemon(node: Node, tmp_path: Path) -> None:
    ep = ["--cmd", node.endpoints["cmd"], "--pub", node.endpoints["pub"]]
    assert run("ctl", "activate", *ep, "--client", "op") == 0
    assert run("ctl", "start_exploration", *ep, "--client", "op") == 0
    png = tmp_path / "live.png"
    assert run("view", *ep, "--png", str(png), "--duration", "20") == 0  # ends on convergence
    assert png.read_bytes()[:4] == b"\x89PNG"
