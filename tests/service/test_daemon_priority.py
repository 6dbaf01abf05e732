"""The loop's thread asks for real-time scheduling and says plainly when it cannot have it."""

from __future__ import annotations

import os
import threading

import pytest

from service.daemon import priority
from service.daemon.priority import Scheduling, set_loop_priority

linux_only = pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO here")


def _in_a_thread(fn):
    """Run `fn` in a fresh thread (scheduling is per thread) and return what it returned."""
    out: list = []
    t = threading.Thread(target=lambda: out.append(fn()))
    t.start()
    t.join()
    return out[0]


@linux_only
def test_the_calling_thread_only_is_raised_or_a_note_says_why() -> None:
    def ask() -> tuple[Scheduling, int]:
        return set_loop_priority(20), os.sched_getscheduler(0) & ~priority_flags()

    got, policy = _in_a_thread(ask)
    if got.policy == "fifo":
        assert policy == os.SCHED_FIFO and got.priority == 20 and got.note is None
    else:  # a machine that forbids it: ordinary scheduling, and what would allow it
        assert policy == os.SCHED_OTHER and "setcap" in got.note
    assert os.sched_getscheduler(0) & ~priority_flags() == os.SCHED_OTHER  # this thread


def priority_flags() -> int:
    return getattr(os, "SCHED_RESET_ON_FORK", 0)


@linux_only
def test_zero_asks_for_nothing() -> None:
    assert _in_a_thread(lambda: set_loop_priority(0)) == Scheduling("other", 0)


@linux_only
def test_a_refusal_never_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(pid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    got = set_loop_priority(20)
    assert got.policy == "other" and got.priority == 0
    assert "Operation not permitted" in got.note and "realtime_priority = 0" in got.note
