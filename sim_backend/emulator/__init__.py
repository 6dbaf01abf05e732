"""Dynamixel Protocol 2.0 servo-bus emulator on a pseudo-terminal (see `bus.ServoBus`)."""

from sim_backend.emulator.bus import FaultPlan, ServoBus
from sim_backend.emulator.servo import EmulatedServo

__all__ = ["EmulatedServo", "FaultPlan", "ServoBus"]
