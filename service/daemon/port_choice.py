"""Which serial ports a client may point the daemon at.

A lease holder's `configure` may name `backend.options.port`, and the daemon opens what it
names and writes Dynamixel packets there, with the daemon's rights (often root, or the
dialout group). A held-out client made it write into terminals (`/dev/pts/1`, `/dev/tty0`)
and learned from the errors whether a path existed. So a client may choose only a port its
operator allowed: one the daemon's own configuration named at start-up, or one that, as
named or with its links followed (`/dev/serial/by-id/...` names link to `/dev/ttyUSB0`),
matches a pattern of `[security] serial_ports`. Any other is refused before anything is
opened, in the same words whether or not it exists. (A pattern in a folder others may
write to, such as /tmp, lets them link a name there to any device.)
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Collection, Iterable

from service.errors import ConfigError


def check_port_choice(port: object, current: object, operator_ports: Collection[str],
                      patterns: Iterable[str]) -> None:
    """Refuse `port` (ConfigError) unless it is the port in use (`current`), one of
    `operator_ports`, or it matches one of `patterns` as named or with its links followed.
    A port that is not a string is left to the backend's own checks."""
    if not isinstance(port, str) or port == current or port in operator_ports:
        return
    patterns = tuple(patterns)
    names = (port, os.path.realpath(port))
    if any(fnmatch.fnmatchcase(name, p) for name in names for p in patterns):
        return
    allowed = ", ".join(patterns) or "none"
    raise ConfigError(
        f"backend.options.port {port!r} is not a port clients may choose: a client may name "
        f"the port in hapticd's own configuration or one matching [security] serial_ports "
        f"({allowed}); its operator can add a pattern there (e.g. \"/dev/pts/*\" to rehearse "
        f"on `haptic emulate`) and restart hapticd")
