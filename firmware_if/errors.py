"""Exceptions raised by the hardware layer: one family, each with the context to act on."""

from __future__ import annotations


class FirmwareError(Exception):
    """Base of every error raised by `firmware_if`."""


class HandConfigError(FirmwareError, ValueError):
    """A hand description or driver setting is invalid; the message names the field to fix."""


class CommunicationError(FirmwareError):
    """A servo did not answer, or answered with a packet we could not use."""

    def __init__(self, message: str, servo_ids: tuple[int, ...] = (), packet: bytes = b"") -> None:
        super().__init__(message)
        self.servo_ids = servo_ids
        self.packet = packet


class BusTimeoutError(CommunicationError):
    """No (complete) status packet arrived before the deadline."""


class StaleReplyError(BusTimeoutError):
    """A reply came, but made before it was asked for: a late answer to an earlier read
    (its own is late in turn)."""


class HardwareFault(FirmwareError):
    """A servo reports a hardware error, or the bus failed too often: torque off, reset needed."""


class PortLost(HardwareFault):
    """The serial port itself failed (adapter unplugged, emulator gone): the bus latched a
    fault; `reset` (or `configure` with a new port) opens the port again."""


class NotReadyError(FirmwareError):
    """The backend was asked to act before it was opened or before a first valid read."""
