"""The daemon's log: every line of either process parses as JSON."""

from __future__ import annotations

import json
import logging

from service.daemon.json_log import JsonFormatter


def test_a_message_with_both_quotes_is_still_a_json_line():
    """The compute process's lines were a Python repr: a message holding both kinds of quote
    (an outline in millimetres: `scenario.object_units = "mm"` and 'obj_mm') came out as
    'object ...', which no JSON reader takes."""
    message = """object 'obj_mm' spans 28.3 m across (give `scenario.object_units = "mm"`)"""
    record = logging.LogRecord("service.daemon.worker", logging.WARNING, __file__, 1, message,
                               None, None)
    record.fields = {"seed": 3}
    line = JsonFormatter(process="worker").format(record)
    assert json.loads(line) == {"t": json.loads(line)["t"], "level": "warning",
                                "event": message, "process": "worker", "seed": 3}
