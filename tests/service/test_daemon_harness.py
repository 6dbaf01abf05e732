"""The harness that runs a node on a thread: a node that will not stop says where it is."""

from __future__ import annotations

import threading

from service.daemon.harness import _where


def test_a_stuck_thread_is_named_where_it_waits() -> None:
    release, waiting = threading.Event(), threading.Event()

    def parked_in_shutdown() -> None:
        waiting.set()
        release.wait()

    thread = threading.Thread(target=parked_in_shutdown, daemon=True)
    thread.start()
    assert waiting.wait(10)
    try:
        where = _where(thread)
    finally:
        release.set()
        thread.join(10)
    assert "in parked_in_shutdown" in where  # the frame it is parked in, by name
    assert _where(thread) == "(gone)"
