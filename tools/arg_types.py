"""Bounded numbers for command-line options, as argparse `type`s: a value out of range, not
finite or not a number is argparse's one-line error naming the option (exit status 2)
before anything starts. A held-out check gave `bench bus --cycles -1`, `bus read --interval
inf` and `bench anytime --budget-ms nan` tracebacks, `bench service --subscribers 100000`
"too many open files", and `--duration inf` a command that never ended."""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable
from typing import Any

from service.bounds import UNITS, bound_of
from service.errors import ConfigError


def integer(lo: int, hi: int) -> Callable[[str], int]:
    """An integer in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi}], got "
                                             f"{text!r}")
        return value

    return parse


def number(lo: float, hi: float, unit: str = "") -> Callable[[str], float]:
    """A finite number in [lo, hi] (`unit` named in the error)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(
                f"must be a number in [{lo:g}, {hi:g}]"
                f"{f' ({UNITS.get(unit, unit)})' if unit else ''}, got "
                f"{text!r}")
        return value

    return parse


def setting(cls: type, name: str) -> Callable[[str], Any]:
    """What the setting `name` of the configuration class `cls` takes (`service.bounds`),
    as the daemon's own configuration would check it: declared once."""
    bound = dataclasses.replace(bound_of(cls, name), optional=False)  # given: a value
    convert = {"int": int, "float": float}[bound.kind]

    def parse(text: str) -> Any:
        try:
            value = convert(text)
        except ValueError:
            value = text
        try:
            return bound.check("value", value)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value ")) from None

    return parse
