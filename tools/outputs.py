"""Output files a command will write, checked before any work: a path that cannot be
written is a one-line error at the start, not a traceback after a long run."""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from service.errors import ConfigError
from tools.signals import signals_held
from tools.words import EXIT_FAULT, command_record, interrupted_status


def check_outputs(*paths: Path | str | None, figures: tuple[Path | str | None, ...] = (),
                  inputs: tuple[Path | str | None, ...] = (), stdout: bool = False) -> None:
    """Refuse any of `paths` (and `figures`, which must be a format matplotlib writes here)
    that cannot be written: its folder missing, it a folder, the system refusing it, one of
    the command's `inputs`, or two outputs one file (a held-out check's `--json
    /sys/x.json` ran every episode, then failed with a traceback; `--plot x.txt` wrote the
    JSON, then failed; `export run.mcap --json run.mcap` overwrote the recording). `-` is
    standard output where the command writes there (`stdout`). A file the check creates is
    removed."""
    outputs = [Path(p) for p in (*paths, *figures) if p is not None]
    for path in outputs:
        if str(path) == "-":
            if stdout:
                continue
            raise ConfigError("'-' is not a file: this command writes its output to files; "
                              "name one")
        _check_writable(path)
        if any(_same_file(path, Path(i)) for i in inputs if i is not None):
            raise ConfigError(f"cannot write {path}: it is an input of this command; name "
                              "another file")
    files = [p for p in outputs if str(p) != "-"]
    for k, path in enumerate(files):
        if any(_same_file(path, other) for other in files[k + 1:]):
            raise ConfigError(f"cannot write {path} twice: give each output its own file")
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


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except OSError:
        return False


@functools.cache
def _figure_formats() -> frozenset[str]:
    """The formats matplotlib writes by itself: not PGF, which needs a TeX installation
    (a held-out check's `--plot x.pgf` passed, then failed after the work)."""
    from matplotlib.figure import Figure

    return frozenset(Figure().canvas.get_supported_filetypes()) - {"pgf"}


def write_episode(report: Any, json_path: Path | str | None, plot_path: Path | str | None,
                  draw: Callable[[Any, Path | str], None], failed: bool) -> int:
    """`haptic run`'s outputs and exit status for one episode (a finger's or a hand's):
    `--json` written whole (a second Ctrl-C waits for it), the figure unless a signal cut
    the run, and the status: 3 after a fault, 128 + the signal after an interrupt, 1 when
    `failed` (a wrong pose, a drop: a script must notice), else 0."""
    cut = report.result.interrupted
    if json_path:
        with signals_held():
            Path(json_path).write_text(json.dumps(command_record(report), indent=1))
        print(f"episode written to {json_path}")
    if plot_path and cut is not None:
        print(f"no figure: the run was interrupted ({plot_path} not written)")
    elif plot_path:
        draw(report, plot_path)
        print(f"figure written to {plot_path}")
    if report.result.fault is not None:
        return EXIT_FAULT
    if cut is not None:
        return interrupted_status(cut)
    return 1 if failed else 0
