"""Torque and the latched fault of a simulated backend: the lifecycle every one shares."""

from __future__ import annotations

from firmware_if.errors import HardwareFault


class FaultLatch:
    """Torque on/off and a latched fault, as servos have them. Subclasses say when they are
    open (`_require_open`)."""

    _torque: bool = False
    _fault: str | None = None

    def _require_open(self) -> None:
        raise NotImplementedError

    def _cut_step(self) -> None:
        """End a step under way where it is, as blocked: servos without torque stop (the
        Dynamixel backends count such a step cut short as blocked too)."""

    def set_torque(self, on: bool) -> None:
        self._require_open()
        if on and self._fault:
            raise HardwareFault(f"cannot enable torque while faulted: {self._fault}; reset first")
        self._torque = on
        if not on:
            self._cut_step()

    def clear_fault(self) -> list[str]:
        self._fault = None
        return []

    def inject_fault(self, reason: str) -> None:
        """Latch a fault (tests and fault drills): torque drops, like a real servo."""
        self._fault = reason
        self._torque = False
        self._cut_step()
