"""The daemon's log format: one JSON object a line, from either of its processes, so a log
reader parses every line (a message with both kinds of quote came out as a Python repr)."""

from __future__ import annotations

import json
import logging
import time
from typing import Any


def json_line(record: logging.LogRecord, **extra: Any) -> str:
    """A record as a JSON line: its time, level and event (the message), then `extra` and
    the record's structured `fields`."""
    out = {"t": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)),
           "level": record.levelname.lower(), "event": record.getMessage(), **extra}
    out.update(getattr(record, "fields", {}) or {})
    return json.dumps(out, default=str)


class JsonFormatter(logging.Formatter):
    """`json_line` for a handler; `extra` goes into every line (the compute process says
    it is the worker)."""

    def __init__(self, **extra: Any) -> None:
        super().__init__()
        self.extra = extra

    def format(self, record: logging.LogRecord) -> str:
        return json_line(record, **self.extra)
