"""The compute process leaves quietly when the daemon goes away, whatever it was doing: no
traceback in the daemon's log, exit status 0, no files of its own left behind."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from dataclasses import asdict
from multiprocessing.connection import Connection
from pathlib import Path

import pytest

from service.episode.scenario import RunSettings
from service.wire import envelope as wire


def start_worker(shm: Path) -> tuple[subprocess.Popen, Connection]:
    """The compute process as the daemon starts it, its shared-memory files under `shm`."""
    ours, theirs = socket.socketpair()
    proc = subprocess.Popen([sys.executable, "-m", "service.daemon.worker",
                             str(theirs.fileno())], pass_fds=[theirs.fileno()],
                            stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "HAPTIC_SHM": str(shm)})
    theirs.close()
    return proc, Connection(ours.detach())


@pytest.mark.parametrize("before_closing", ["nothing", "setup"])
def test_the_daemon_closing_its_end_ends_the_process_quietly(before_closing: str,
                                                             tmp_path: Path) -> None:
    proc, conn = start_worker(tmp_path)
    if before_closing == "setup":  # the reply to it will find the socket closed
        settings = RunSettings(map="peaks:20")
        conn.send_bytes(wire.encode("setup", 1, {"req": 1, "settings": asdict(settings),
                                                 "backend": "sim", "cloud_points": 50}))
    conn.close()
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0 and stderr == ""
    assert list(tmp_path.iterdir()) == []  # the map it wrote for the daemon is gone too


def test_exit_is_answered_by_exiting(tmp_path: Path) -> None:
    proc, conn = start_worker(tmp_path)
    conn.send_bytes(wire.encode("exit", 1, {}))
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0 and stderr == ""
    conn.close()
