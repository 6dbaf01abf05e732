"""The machine's own timing floor: the daemon's loop with nothing in its ticks.

A loop on a virtual machine wakes late even when idle (a halted vCPU takes the hypervisor
a millisecond or more to resume: on this project's 2-core KVM machine a bare 200 Hz sleep
loop has lateness p99 ~1.3 ms). Soak figures are read against this floor, measured the
same way on the same machine just before.
"""

from __future__ import annotations

import threading
import time

from service.daemon.loop import RateLoop
from service.daemon.priority import set_loop_priority


def wake_floor(rate_hz: float, seconds: float, priority: int) -> dict[str, float | str]:
    """Run an empty `RateLoop` for `seconds` in a thread scheduled as the daemon's loop
    (`priority`, see service.daemon.priority); its period percentiles, ms."""
    result: dict[str, float | str] = {}

    def run() -> None:
        scheduling = set_loop_priority(priority)
        loop = RateLoop(int(round(1e9 / rate_hz)), lambda tick: None)
        end = time.monotonic() + seconds
        loop.run(lambda: time.monotonic() >= end)
        set_loop_priority(0)
        p = loop.summary()
        result.update(scheduling=scheduling.policy, period_p50_ms=p["period_p50_ms"],
                      period_p99_ms=p["period_p99_ms"], period_max_ms=p["period_max_ms"])

    thread = threading.Thread(target=run, name="wake-floor")
    thread.start()
    thread.join()
    return result
