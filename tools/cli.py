"""The `haptic` command line: a table of subcommands, each imported only when it runs.

`haptic --help` lists COMMANDS from this table alone; `haptic CMD ...` imports CMD's module
and nothing else, so an operator command (`ctl`, `watch`) never pays for numba or scipy.
To add a command, add one row: its name, "module" or "module:function" (default
function `register`), and a one-line summary. The function receives the command's own
`argparse.ArgumentParser` (already named and described) and adds its options and
`parser.set_defaults(handler=...)`; it should import heavy libraries inside the handler.

A user error prints one line and exits with status 2, never a traceback. SIGINT and
SIGTERM end a command cleanly (its `finally` blocks run, files are closed), also when
started in the background; a closed pipe (`| head`) ends it quietly.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NoReturn

from firmware_if.errors import FirmwareError
from service.errors import InputError, ServiceError
from tools.signals import signals_interrupt

WRITE_FAILURES = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO})
"""OS errors of an output that passed its check and failed as it was written (a full
disk, `--json /dev/full`): one line, not a traceback."""

GROUPS = ("bench", "bus", "map")
"""Commands whose next word names a command of its own (`haptic bench paper`)."""

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("tools.run_cli", "localize a simulated (or real) finger once, step by step"),
    "bench": ("tools.bench", "run a seeded benchmark scenario of BENCHMARKS.md (B1-B6 and more; "
                             "`haptic bench --help` lists them)"),
    "explore": ("tools.ctl_cli:register_explore",
                "localize with a running hapticd: take control, activate, explore until "
                "converged (exit 0), release"),
    "ctl": ("tools.ctl_cli:register_ctl", "send one command to hapticd (the commands and "
                                          "their arguments are listed in its help)"),
    "watch": ("tools.stream_cli:register_watch", "print hapticd's stream as text"),
    "view": ("tools.view_cli", "draw hapticd's belief live, or a snapshot to a PNG"),
    "record": ("tools.record_cli:register_record",
               "record hapticd's stream to an MCAP file (Foxglove and ROS 2 tools read it)"),
    "replay": ("tools.record_cli:register_replay",
               "print or re-publish a recording (.mcap, or an older .hrec)"),
    "export": ("tools.record_cli:register_export",
               "write a recording's episodes as JSON (haptic run --json's format) or CSV"),
    "keygen": ("tools.stream_cli:register_keygen",
               "write a CurveZMQ key pair (NAME.key public, NAME.key_secret secret)"),
    "map": ("tools.map_cli", "list, check or build height maps"),
    "campaign": ("tools.campaign_cli", "run a grid of benchmark scenarios from a TOML file "
                                       "(resumable; a local pool or a Dask cluster)"),
    "emulate": ("tools.emulate_cli", "emulate a Dynamixel hand on a pseudo-terminal"),
    "bus": ("tools.bus_cli", "scan, read or check a Dynamixel servo bus"),
}
"""name -> ("module[:function]", summary)."""


Register = Callable[[argparse.ArgumentParser], None]
"""Adds a command's options and `set_defaults(handler=...)` to its parser."""


class HelpFormatter(argparse.HelpFormatter):
    """Wraps one-paragraph texts; keeps texts with line breaks (tables, examples) as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if "\n" in text:
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


class IntermixedParser(argparse.ArgumentParser):
    """Options and positionals in any order (`ctl configure --client me changes=...`); a bad
    option's error in one line, as every other refusal, without the usage block."""

    _mixing = False

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (`{self.prog} --help` lists the "
                     "options)\n")

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        if self._mixing or self._subparsers is not None:
            return super().parse_known_args(args, namespace)
        self._mixing = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._mixing = False


class LazyCommands(argparse._SubParsersAction):
    """Subcommands listed up front whose options are registered only when one is chosen."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._pending: dict[str, Register] = {}

    def add_lazy(self, name: str, summary: str,
                 register: Register) -> argparse.ArgumentParser:
        parser = self.add_parser(name, help=summary, formatter_class=HelpFormatter,
                                 description=summary[:1].upper() + summary[1:] + ".")
        self._pending[name] = register
        return parser

    def register_all(self) -> None:
        """Register every pending command now (for tools that walk the whole parser)."""
        for name in list(self._pending):
            self._pending.pop(name)(self._name_parser_map[name])

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        register = self._pending.pop(values[0], None)
        if register is not None:
            register(self._name_parser_map[values[0]])
        super().__call__(parser, namespace, values, option_string)


def importer(target: str) -> Register:
    """The registration function "module[:function]" names (default `register`)."""
    module, _, function = target.partition(":")

    def register(parser: argparse.ArgumentParser) -> None:
        getattr(importlib.import_module(module), function or "register")(parser)

    return register


def add_lazy_commands(parser: argparse.ArgumentParser, table: dict[str, tuple[str, str]],
                      dest: str, metavar: str,
                      loader: Callable[[str], Register] = importer) -> LazyCommands:
    """Subcommands from a {name: (target, summary)} table; `loader(target)` registers one."""
    sub = parser.add_subparsers(dest=dest, metavar=metavar, required=True,
                                action=LazyCommands, parser_class=IntermixedParser)
    for name, (target, summary) in table.items():
        sub.add_lazy(name, summary, loader(target))
    return sub


def build_parser() -> argparse.ArgumentParser:
    """The whole command line; a command's module is imported when that command is parsed."""
    parser = argparse.ArgumentParser(
        prog="haptic", description="Haptic localization: a rolling fingertip finds its pose "
        "on a known surface. `haptic COMMAND --help` explains each command.")
    add_lazy_commands(parser, COMMANDS, dest="command", metavar="COMMAND")
    return parser


@contextmanager
def _one_blas_thread() -> Iterator[None]:
    """One BLAS thread, as in the daemon: at our sizes threads only add handover stalls.
    Libraries not loaded yet read the environment; loaded ones are limited directly."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if "numpy" not in sys.modules:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


def _quiet_broken_pipe() -> None:
    """Stdout's reader went away (`| head`): send the rest nowhere and leave quietly."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _name(argv: list[str]) -> str:
    """The command's name for messages: its first word, and the second for a group's
    (`bench scale`; the top level has no options)."""
    words = argv[:2] if argv and argv[0] in GROUPS else argv[:1]
    return " ".join(w for w in words if not w.startswith("-"))


COMMA_VALUES = ("--start",)
"""Options whose value is numbers separated by commas, which may begin with a minus."""


def _glued(argv: list[str]) -> list[str]:
    """`--start -0.01,0.05,0` as `--start=-0.01,0.05,0`: argparse takes a value that starts
    with "-" and is no plain number for an option, and said only "expected one argument"
    (a held-out researcher's start beside the map's edge)."""
    out: list[str] = []
    for token in argv:
        if (out and out[-1] in COMMA_VALUES and token.startswith("-") and "," in token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = _glued(sys.argv[1:] if argv is None else list(argv))
    try:  # around the set-up too: a signal can land while the handlers are being installed
        with signals_interrupt(), _one_blas_thread():
            args, unknown = build_parser().parse_known_args(argv)
            if unknown:  # in the command's one line, not the top level's usage block
                name = _name(argv)
                print(f"haptic {name}: error: unrecognized arguments: {' '.join(unknown)} "
                      f"(`haptic {name} --help` lists the options)", file=sys.stderr)
                return 2
            return int(args.handler(args) or 0)
    except (InputError, FirmwareError) as exc:
        print(f"haptic {_name(argv)}: error: {exc}", file=sys.stderr)
        return 2
    except ServiceError as exc:
        print(f"haptic {_name(argv)}: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        _quiet_broken_pipe()
        return 0
    except OSError as exc:
        if exc.errno not in WRITE_FAILURES:
            raise
        # the outputs were checked before the work (`tools.outputs`); a disk can still fill
        where = f" {exc.filename}" if exc.filename else ""
        print(f"haptic {_name(argv)}: error: cannot write{where}: {exc.strerror}; free some "
              "space or write elsewhere", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        print(f"haptic {_name(argv)}: interrupted", file=sys.stderr)
        return 128 + int(signum)


if __name__ == "__main__":
    sys.exit(main())
