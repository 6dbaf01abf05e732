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


def test_the_servo_librarys_warnings_are_json_lines_too(capsys) -> None:
    """hapticd's stderr is JSON lines (README): a held-out lab's reader met the warning of
    servos the hand does not use as a plain line, which Python's last-resort handler wrote
    for the `haptic.servos` logger."""
    import logging

    from service.daemon.main import LOGGERS, log_json_lines

    kept = {name: (logging.getLogger(name).handlers[:], logging.getLogger(name).propagate,
                   logging.getLogger(name).level) for name in LOGGERS}
    try:
        log_json_lines("INFO")
        logging.getLogger("haptic.servos").warning("warning: %s", "servo 9 also answers")
        logging.getLogger("hapticd").info("lifecycle")
        lines = capsys.readouterr().err.splitlines()
    finally:
        for name, (handlers, propagate, level) in kept.items():
            logger = logging.getLogger(name)
            logger.handlers[:], logger.propagate = handlers, propagate
            logger.setLevel(level)
    records = [json.loads(line) for line in lines]
    assert len(records) == 2 and "servo 9 also answers" in json.dumps(records[0])
