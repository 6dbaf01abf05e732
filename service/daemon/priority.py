"""Real-time scheduling for the control loop's thread, where the machine allows it.

On a loaded 2-core machine an ordinary thread waits behind the compute process and every
subscriber for its wake-up and is preempted mid-tick: a tick then starts milliseconds late
or overruns its period though its own work takes 2 ms. Control stacks that hold their rate
(ros2_control's controller manager, for one) run the loop thread under SCHED_FIFO and say
so when they cannot. Only the loop thread is raised: the command handling inside its waits
is short, and the compute process stays an ordinary (niced) process.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Scheduling:
    """What the loop thread runs under, for the log and `status`."""

    policy: str
    """'fifo' or 'other' (the ordinary time-sharing scheduler)."""
    priority: int
    note: str | None = None
    """Why the asked-for priority was not applied, and what would allow it."""


def set_loop_priority(priority: int) -> Scheduling:
    """Put the calling thread (the loop's) under SCHED_FIFO at `priority` (1-98); 0 leaves
    it ordinary. Never raises: a machine that forbids it keeps the ordinary scheduler, with
    a note."""
    return set_thread_priority(priority, "the loop keeps ordinary scheduling and may miss "
                               "its period on a loaded machine",
                               "set loop.realtime_priority = 0 to stop asking")


def set_thread_priority(priority: int, refused: str, stop_asking: str) -> Scheduling:
    """Put the calling thread under SCHED_FIFO at `priority`, or say why not: `refused`
    says what that costs, `stop_asking` how to ask for nothing."""
    fifo = getattr(os, "SCHED_FIFO", None)
    if fifo is None:
        return Scheduling("other", 0, None if priority == 0 else
                          "real-time scheduling is not available on this platform")
    try:
        if priority == 0:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            return Scheduling("other", 0)
        # a process forked from this thread (the compute process, restarted after a
        # crash) stays ordinary
        os.sched_setscheduler(0, fifo | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(priority))
    except OSError as exc:
        return Scheduling("other", 0, (
            f"SCHED_FIFO {priority} refused ({exc.strerror}): {refused}; allow it with "
            "`setcap cap_sys_nice+ep` on the Python binary, an rtprio limit in "
            f"/etc/security/limits.conf, or {stop_asking}"))
    return Scheduling("fifo", priority)
