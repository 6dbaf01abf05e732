"""`hapticd`: the haptic localization daemon.

    hapticd --sim                  simulated finger, default config, loopback endpoints
    hapticd --config hapticd.toml  as configured (config/hapticd.toml is the sample)

Logs are JSON lines on stderr (the first, `listening`, names the bound endpoints).
SIGINT, SIGTERM and SIGHUP (not under `nohup`: `service.signals`) stop the loop; shutdown
turns torque off, publishes a final `shutdown` event and closes the sockets. Exit status:
0 after a clean stop, 2 for a bad config.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys

from firmware_if.errors import FirmwareError
from service.daemon.config import DaemonConfig, load_config
from service.daemon.json_log import JsonFormatter
from service.daemon.node import Node
from service.daemon.quiet_files import lab_reads
from service.errors import InputError
from service.signals import stop_signals
from service.wire.client import ENDPOINT_ENV


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hapticd", description="Haptic localization daemon.")
    p.add_argument("--config", metavar="FILE", help="TOML config (see config/hapticd.toml)")
    p.add_argument("--sim", action="store_true",
                   help="use the simulated backend whatever the config says")
    p.add_argument("--pub", metavar="ENDPOINT", default=os.environ.get(ENDPOINT_ENV["pub"]),
                   help=f"override endpoints.pub (default: ${ENDPOINT_ENV['pub']} if set)")
    p.add_argument("--cmd", metavar="ENDPOINT", default=os.environ.get(ENDPOINT_ENV["cmd"]),
                   help=f"override endpoints.cmd (default: ${ENDPOINT_ENV['cmd']} if set)")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning"])
    return p


def config_from_args(args: argparse.Namespace) -> DaemonConfig:
    with lab_reads():
        config = load_config(args.config) if args.config else DaemonConfig()
    if args.sim and config.backend.name != "sim":
        config = config.updated({"backend": {"name": "sim", "options": {}}})
    if args.pub or args.cmd:
        ep = dataclasses.replace(config.endpoints, pub=args.pub or config.endpoints.pub,
                                 cmd=args.cmd or config.endpoints.cmd)
        config = dataclasses.replace(config, endpoints=ep)
    return config


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever `sys.stderr` is at the time: a handler holding the stream it was
    made with wrote into a closed file once that stream was replaced (pytest's capture)."""

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value: object) -> None:
        pass


LOGGERS = ("hapticd", "haptic")
"""The daemon's own records, and the library's it runs (`haptic.servos`: servos on the
bus the hand does not use): a held-out lab's JSON-lines reader met that warning as a plain
line, which Python's last-resort handler wrote."""


def log_json_lines(level: str) -> None:
    """Every record of `LOGGERS` as one JSON line on stderr (the README's log format)."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        if not logger.handlers:
            handler = _StderrHandler()
            handler.setFormatter(JsonFormatter())
            logger.addHandler(handler)
        logger.setLevel(level)
        logger.propagate = False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    log_json_lines(args.log_level.upper())
    try:
        config = config_from_args(args)
    except InputError as exc:
        print(f"hapticd: error: {exc}", file=sys.stderr)
        return 2
    node = Node(config)

    def on_signal(signum: int, frame: object) -> None:
        node.stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in stop_signals()}
    try:
        node.serve()
    except (InputError, FirmwareError) as exc:
        print(f"hapticd: error: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
