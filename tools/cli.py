"""The `haptic` command line: one subcommand module per job, each with `register(subparsers)`.

Subcommand modules are imported by name, so `service` never loads a backend or a tool it
does not need. A user error prints one line and exits with status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from threadpoolctl import threadpool_limits

from firmware_if.errors import FirmwareError
from service.errors import InputError, ServiceError

SUBCOMMAND_MODULES = (
    "tools.run_cli",        # haptic run
    "tools.bench",          # haptic bench
    "tools.map_cli",        # haptic map
    "tools.emulate_cli",    # haptic emulate
    "tools.bus_cli",        # haptic bus
    "tools.stream_cli",     # haptic watch / ctl / record / replay / view / keygen
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="haptic", description="Haptic localization: a rolling fingertip finds its pose.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with threadpool_limits(limits=1):  # as in the daemon: no BLAS thread handovers
            return int(args.handler(args) or 0)
    except (InputError, FirmwareError) as exc:
        print(f"haptic {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ServiceError as exc:
        print(f"haptic {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"haptic {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
