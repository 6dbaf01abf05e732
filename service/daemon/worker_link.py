"""The loop's end of the compute process (`service.daemon.worker`): start it, send it
requests, collect its replies without ever waiting, and notice when it dies.

The process is a fresh interpreter (`python -m service.daemon.worker FD`, the spawn
start method without multiprocessing's re-import of the parent's main script) talking over
a socket pair with `multiprocessing.connection`'s framing; nothing is pickled. Only the loop
thread uses a link. `poll()` returns the replies that have arrived (a read of a few
kilobytes); a request is one small write. If the process dies, `poll()` raises WorkerDied
once and the next `start()` (the next configure) starts a new one.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from typing import Any

from service.errors import ServiceError
from service.wire import envelope as wire


class WorkerDied(ServiceError):
    """The compute process exited (a crash in a localizer, or killed)."""


class WorkerLink:
    """Requests to, and replies from, the compute process."""

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._reqs = itertools.count(1)
        self._seq = 0

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> None:
        """Start the process if it is not running (it imports and compiles for a second;
        requests sent meanwhile wait in the socket)."""
        if self.alive:
            return
        self.close()
        ours, theirs = socket.socketpair()
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "service.daemon.worker", str(theirs.fileno())],
                pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())

    def send(self, kind: str, **fields: Any) -> int:
        """Send a request; returns its `req` number (replies carry it)."""
        if self._conn is None:
            raise WorkerDied("the compute process is not running")
        req = next(self._reqs)
        self._seq += 1
        try:
            self._conn.send_bytes(wire.encode(kind, self._seq, {"req": req, **fields}))
        except (OSError, ValueError) as exc:
            self._lost()
            raise WorkerDied(f"the compute process died ({exc})") from None
        return req

    def poll(self, timeout_s: float = 0.0) -> list[wire.Message]:
        """Every reply that has arrived (waiting up to `timeout_s` for one: tests only, the
        loop never waits); WorkerDied if the process has gone."""
        if self._conn is None:
            return []
        out = []
        try:
            wait = timeout_s
            while self._conn.poll(wait):
                wait = 0
                out.append(wire.decode(self._conn.recv_bytes()))
        except (EOFError, OSError) as exc:
            self._lost()
            raise WorkerDied(f"the compute process died ({exc or 'pipe closed'})") from None
        if not out and self._process.poll() is not None:
            code = self._process.returncode
            self._lost()
            raise WorkerDied(f"the compute process died (exit code {code})")
        return out

    def _lost(self) -> None:
        with contextlib.suppress(OSError):
            self._conn.close()
        self._conn = None
        self._process = None

    def close(self, timeout_s: float = 2.0) -> None:
        """Ask the process to exit, then make sure it has."""
        if self._conn is not None:
            with contextlib.suppress(OSError, ValueError):
                self._conn.send_bytes(wire.encode("exit", self._seq + 1, {}))
            with contextlib.suppress(OSError):
                self._conn.close()
            self._conn = None
        if self._process is not None:
            try:
                self._process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait(timeout_s)
            self._process = None

    def kill(self) -> None:
        """Kill the process outright (fault drills and tests)."""
        if self._process is not None:
            self._process.kill()
            self._process.wait(10)
