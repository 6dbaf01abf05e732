"""The machine's own timing floor: the daemon's loop with nothing in its ticks.

A loop on a virtual machine wakes late even when idle (a halted vCPU takes the hypervisor
a millisecond or more to resume: on this project's 2-core KVM machine a bare 200 Hz sleep
loop, idle, woke late by p99 0.9-1.6 ms over six runs). Soak figures are read against
this floor, measured the same way on the same machine just before.
"""

from __future__ import annotations

import threading
import time

from service.daemon.loop import RateLoop
from service.daemon.priority import set_loop_priority


def wake_floor(rate_hz: float, seconds: float, priority: int) -> dict[str, float | str]:
    """Run an empty `RateLoop` for `seconds` in a thread scheduled as the daemon's loop
    (`priority`, see service.daemon.priority); its period percentiles, ms, exact over every
    tick (as the soak's reader times the daemon), not the whole-run histogram's."""
    result: dict[str, float | str] = {}

    def run() -> None:
        scheduling = set_loop_priority(priority)
        loop = RateLoop(int(round(1e9 / rate_hz)), lambda tick: None)
        end = time.monotonic() + seconds
        loop.run(lambda: time.monotonic() >= end)
        p = loop.summary(window=loop.ticks)  # the thread ends here: its scheduling with it
        result.update(scheduling=scheduling.policy, period_p50_ms=p["period_p50_ms"],
                      period_p99_ms=p["period_p99_ms"], period_max_ms=p["period_max_ms"])

    thread = threading.Thread(target=run, name="wake-floor")
    thread.start()
    thread.join()
    return result
