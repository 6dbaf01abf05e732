"""Test-wide settings: property tests are derandomized so every run is the same run, and
the daemon's logger is left as each test found it."""

import logging
from collections.abc import Iterator

import pytest
from hypothesis import settings

settings.register_profile("haptic", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("haptic")


@pytest.fixture(autouse=True)
def _hapticd_logger_as_it_was() -> Iterator[None]:
    """`hapticd`'s `main` gives the `hapticd` logger its stderr handler for the process. A
    test that runs `main` in-process must not hand it on: later tests' in-process daemons
    then wrote from their threads between tests, past pytest's capture."""
    logger = logging.getLogger("hapticd")
    handlers, propagate, level = list(logger.handlers), logger.propagate, logger.level
    yield
    logger.handlers[:] = handlers
    logger.propagate, logger.level = propagate, level
