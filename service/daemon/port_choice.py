"""Which serial ports a client may point the daemon at.

A lease holder's `configure` may name `backend.options.port`, and the daemon opens what it
names and writes Dynamixel packets there, with the daemon's rights (often root, or the
dialout group). A held-out client made it write into terminals (`/dev/pts/1`, `/dev/tty0`)
and learned from the errors whether a path existed. So a client may choose only a port its
operator allowed: one the daemon's own configuration named at start-up, or one whose real
path (links followed, `..` resolved) matches a pattern of `[security] serial_ports`, where
`*` stays within one folder. The daemon then holds the real path, not the name: a second
held-out check re-pointed an accepted link at a terminal after the check (and again before
a `reset`), and matched `/dev/pts/../ptmx` against `/dev/pts/*` as text. Any other port is
refused before anything is opened, in the same words whether or not it exists.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Iterable
from pathlib import PurePosixPath

from service.errors import ConfigError


def chosen_port(port: object, current: object, operator_ports: Collection[str],
                patterns: Iterable[str]) -> object:
    """The port to hold for a client's `port`: as named if it is the port in use
    (`current`) or one of `operator_ports`, else its real path if that matches one of
    `patterns`; ConfigError for any other. A port that is not a string is returned for the
    backend's own checks to name."""
    if not isinstance(port, str):
        return port
    if "\0" not in port and (port == current or port in operator_ports):
        return port
    patterns = tuple(patterns)
    real = os.path.realpath(port) if "\0" not in port else ""
    if real and any(PurePosixPath(real).match(p) for p in patterns):
        return real
    allowed = ", ".join(patterns) or "none"
    raise ConfigError(
        f"backend.options.port {port!r} is not a port clients may choose: a client may name "
        f"the port in hapticd's own configuration or one whose real path matches [security] "
        f"serial_ports ({allowed}); its operator can add a pattern there (e.g. "
        f"\"/dev/pts/*\" to rehearse on `haptic emulate`) and restart hapticd")


def check_patterns(patterns: Iterable[str]) -> None:
    """ConfigError for a pattern that is not an absolute path: a relative one would match
    a name in any folder, and an empty one nothing."""
    for p in patterns:
        if not p.startswith("/"):
            raise ConfigError(f"security.serial_ports: {p!r} is not an absolute path pattern "
                              "such as /dev/ttyUSB*")
