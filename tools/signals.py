"""SIGINT, SIGTERM and SIGHUP for `haptic` commands: they unwind a command like Ctrl-C.

The handler raises `Interrupted` in the main thread, so `finally` blocks run (files closed,
torque released), also in a background job where the shell starts us with SIGINT ignored.
`signals_held` defers it past a block that must finish whole; waiting loops also check
`interrupted()`, since Python drops an exception raised inside a __del__ or a weakref
callback. The state lives here, in one module: under `python -m tools.cli` the entry
module is loaded twice (as __main__ and as tools.cli), and state kept there was two.

The signals are `service.signals.stop_signals`: SIGHUP too, unless under `nohup`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TypeVar

from service.signals import stop_signals

T = TypeVar("T")




class Interrupted(KeyboardInterrupt):
    """A stop signal: unwinds like Ctrl-C so files are closed and torque released."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_seen: dict[str, int | None] = {"signum": None}
_hold = {"depth": 0, "pending": None}
"""While `signals_held` is open: the signal that arrived meanwhile, raised when it closes."""


def interrupted() -> bool:
    """Whether a stop signal has arrived during this command. Waiting loops check it
    besides catching Interrupted: raised while Python runs a weakref callback or a __del__
    (an import's lock clean-up, say), an exception is printed and dropped, and the signal
    with it (a background `watch` ran on after its SIGTERM, once in ~500 tries)."""
    return _seen["signum"] is not None


def _on_signal(signum: int, frame: object) -> None:
    _seen["signum"] = signum
    if _hold["depth"]:
        _hold["pending"] = signum  # raised when the held block ends
        return
    raise Interrupted(signum)


@contextmanager
def signals_interrupt() -> Iterator[None]:
    """The stop signals raise Interrupted in the main thread, even in a background job
    (where the shell starts us with SIGINT ignored), until the command returns."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    _seen["signum"] = None
    try:  # a signal may land between the two installs: the first is restored all the same
        for sig in stop_signals():
            previous[sig] = signal.signal(sig, _on_signal)
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def closed_whole(backend: T) -> T:
    """`backend` with its `close` (torque off, then the port released) run whole: a second
    Ctrl-C waits for it (`signals_held`). The first ends the run and the runner closes
    the backend; a second, landing inside the torque-off exchange, could cut it."""
    close = backend.close  # type: ignore[attr-defined]

    def close_whole() -> None:
        with signals_held():
            close()

    backend.close = close_whole  # type: ignore[attr-defined]
    return backend


@contextmanager
def signals_held() -> Iterator[None]:
    """The stop signals wait until the block is done (a packet exchange on a bus, a record
    written whole), then end the command as usual."""
    _hold["depth"] += 1
    try:
        yield
    finally:
        _hold["depth"] -= 1
        signum = _hold["pending"]
        if signum is not None and _hold["depth"] == 0:
            _hold["pending"] = None
            raise Interrupted(signum)
