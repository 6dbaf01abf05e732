"""Exceptions raised by the service: one family, split by what the user should do."""

from __future__ import annotations


class ServiceError(Exception):
    """Base of every error raised by `service`."""


class InputError(ServiceError, ValueError):
    """Something the user gave us is wrong; the message names it and says what to do."""


class MapError(InputError):
    """A height map could not be loaded or is not a valid surface."""


class ObjectError(InputError):
    """An object's contour could not be loaded or is not a valid closed contour."""


class ConfigError(InputError):
    """A setting or configuration file is invalid."""


class StateError(ServiceError):
    """A request is not allowed in the current lifecycle state."""
