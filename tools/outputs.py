"""Output files a command will write, checked before any work: a path that cannot be
written is a one-line error at the start, not a traceback after a long run."""

from __future__ import annotations

import functools
import os
from pathlib import Path

from service.errors import ConfigError


def check_outputs(*paths: Path | str | None, figures: tuple[Path | str | None, ...] = ()
                  ) -> None:
    """Refuse any of `paths` (and `figures`, which must be a format matplotlib writes) that
    cannot be written: its folder missing, it a folder, or the system refusing it (a
    held-out check's `--json /sys/x.json` ran every episode, then failed with a traceback;
    `--plot x.txt` wrote the JSON, then failed). A file the check creates is removed."""
    for path in (*paths, *figures):
        if path is None or str(path) == "-":
            continue
        _check_writable(Path(path))
    for path in figures:
        if path is None:
            continue
        suffix = Path(path).suffix.lower().lstrip(".")
        if suffix not in _figure_formats():
            raise ConfigError(f"cannot draw {path}: a figure is one of "
                              f"{', '.join('.' + s for s in sorted(_figure_formats()))}; "
                              "name it e.g. figure.png")


def _check_writable(path: Path) -> None:
    folder = path.resolve().parent
    if not folder.is_dir():
        raise ConfigError(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise ConfigError(f"cannot write {path}: it is a folder; name a file in it")
    existed = path.exists()
    try:
        with path.open("a"):
            pass
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}; choose another "
                          "path") from None
    if not existed:
        os.unlink(path)


@functools.cache
def _figure_formats() -> frozenset[str]:
    from matplotlib.figure import Figure

    return frozenset(Figure().canvas.get_supported_filetypes())
