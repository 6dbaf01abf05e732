"""What a remote client learns when a file it named cannot be used: that it cannot, and
nothing about the daemon's files. Whether a path exists, and what a file holds (a CSV's
first cell, a TOML file's line and column), are not the business of a client; the detail
goes to the daemon's log, where the lab that runs it reads it. Presets are not files, and
their errors pass unchanged. The command-line tools keep the full message, and so does
`hapticd` reading its own config file at start-up (`lab_reads`): its reader is the lab."""

from __future__ import annotations

import contextlib
import difflib
import logging
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path

from firmware_if.hand import presets
from service.errors import ConfigError, InputError
from service.localization.maps import MAP_FILE_SUFFIXES
from service.localization.objects.files import OBJECT_FILE_SUFFIXES

_LAB_READS: ContextVar[bool] = ContextVar("lab_reads", default=False)


@contextlib.contextmanager
def lab_reads() -> Iterator[None]:
    """Within it, a file that cannot be used is told in full: the lab reads the error (a
    daemon refusing its own config file printed "the daemon's log says which" under the
    log line that said it)."""
    token = _LAB_READS.set(True)
    try:
        yield
    finally:
        _LAB_READS.reset(token)


def is_map_file(spec: str) -> bool:
    return Path(spec).suffix.lower() in MAP_FILE_SUFFIXES or "/" in spec


def is_object_file(spec: str) -> bool:
    return Path(spec).suffix.lower() in OBJECT_FILE_SUFFIXES


def quiet_file_error(what: str, spec: str, exc: Exception, expected: str,
                     error: type[InputError], hint: str = "") -> InputError:
    """`error` saying only that the `what` file `spec` cannot be used, and what it must be
    (`expected`), then `hint`; `exc`, the reason, is logged (or, where the `lab_reads`,
    given in the error)."""
    if _LAB_READS.get():
        reason = str(exc).removeprefix(f"{spec}: ")
        return error(f"{what} file '{spec}' cannot be used: {reason}"
                     + ("" if "preset" in reason else hint))
    logging.getLogger("hapticd.worker").warning("%s %s: %s", what, spec, exc)
    return error(f"{what} file '{spec}' cannot be used: it is missing, unreadable or not "
                 f"{expected} (the daemon's log says which){hint}")


def quiet_hand_error(spec: str, exc: Exception, holding: bool = False) -> ConfigError:
    """A hand that does not load: a preset's error as it is, a file's quieted, and a name
    that is neither a preset nor shaped like a file's path (no '/', no .toml) told so, with
    the preset it is nearest. (A held-out client's `four-finger` was "a hand file that
    cannot be used": which says nothing of any file, as this says nothing either.)"""
    if spec in presets():
        return ConfigError(str(exc))
    names = presets(holding)  # `holding`: for an object, only hands that can hold one
    if "/" not in spec and not spec.lower().endswith(".toml"):
        near = difflib.get_close_matches(spec, names, n=1, cutoff=0.8)
        return ConfigError(f"no hand preset '{spec}'"
                           + (f" (did you mean '{near[0]}'?)" if near else "")
                           + f": the presets are {', '.join(names)}; a hand file is "
                           "named by its path, ending in .toml")
    return quiet_file_error("hand", spec, exc, "a hand description in TOML", ConfigError,
                            hint=f"; the presets are {', '.join(names)}")
