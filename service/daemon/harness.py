"""Run a daemon node in a background thread: for tests, benchmarks and embedding.

The node's sockets and backend live on that thread only; callers talk to it over its
endpoints like any other client.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import threading
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from service.daemon.config import DaemonConfig, EndpointConfig
from service.daemon.node import Node
from service.errors import ServiceError


def loopback_config(changes: dict[str, Any] | None = None, **endpoint: Any) -> DaemonConfig:
    """Defaults on ephemeral loopback ports (tcp://127.0.0.1:*) with `changes` applied."""
    ep = EndpointConfig(pub="tcp://127.0.0.1:*", cmd="tcp://127.0.0.1:*", **endpoint)
    config = dataclasses.replace(DaemonConfig(), endpoints=ep)
    return config.updated(changes) if changes else config


@contextmanager
def running_node(config: DaemonConfig, timeout_s: float = 60.0) -> Iterator[Node]:
    """A serving node, configured (its compute process started); stopped and joined on exit.
    `timeout_s` is generous: the compute process imports and warms up numba on a loaded
    machine."""
    node = Node(config)

    def serve() -> None:
        with contextlib.suppress(BaseException):  # kept in node.error, re-raised below
            node.serve()

    thread = threading.Thread(target=serve, name="hapticd-node", daemon=True)
    thread.start()
    if not node.ready.wait(timeout_s):
        node.stop()
        raise ServiceError("node did not start in time")
    if node.error is not None:
        thread.join(timeout_s)
        raise node.error
    try:
        yield node
    finally:
        node.stop()
        thread.join(timeout_s)
        if thread.is_alive():
            raise ServiceError(f"node did not stop in time; it is at:\n{_where(thread)}")


def _where(thread: threading.Thread) -> str:
    """The thread's stack, so a node that will not stop says where it is stuck (seen once
    under load, not reproduced since)."""
    frame = sys._current_frames().get(thread.ident or -1)
    return "".join(traceback.format_stack(frame)) if frame is not None else "(gone)"
