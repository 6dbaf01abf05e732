"""A `reset` in progress, off the loop: the backend re-opens its port and configures every
servo again (rebooting those that report a hardware error) on a thread of its own.

In the loop's tick it stopped the state stream and every reply for as long as it took: up
to 1.54 s in a held-out client's campaign, a servo's pings waiting out their timeouts. The
loop leaves the backend be meanwhile, and ends the reset (`Node._end_reset`) once the
thread is done: the lifecycle turns, or the reply says why not.
"""

from __future__ import annotations

import threading

from firmware_if.backend import Backend
from service.wire.commands import Deferred


class Reset:
    """One reset's thread, what it found, and the reply it owes."""

    def __init__(self, backend: Backend, deferred: Deferred, fault_count: int) -> None:
        self.backend = backend
        self.deferred = deferred
        self.fault_count = fault_count
        """Faults latched before it began: one latched since (an `estop`) voids it."""
        self.rebooted: list[str] = []
        self.error: Exception | None = None
        self._thread = threading.Thread(target=self._run, name="hapticd-reset", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.rebooted = list(self.backend.clear_fault())
        except Exception as exc:  # noqa: BLE001 - a FirmwareError, or a bug: the reply says
            self.error = exc

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self) -> None:
        """Let the thread end (a shutdown closes the backend after it)."""
        self._thread.join()
