"""The signals that stop a process: SIGHUP too, unless `nohup` asked it to stay."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PRINT_STOPS = ("from service.signals import stop_signals; "
               "print(sorted(int(s) for s in stop_signals()))")


def stops_of_a_process(ignore_hup: bool) -> list[int]:
    out = subprocess.run(
        [sys.executable, "-c", PRINT_STOPS], cwd=ROOT, capture_output=True, text=True,
        check=True, preexec_fn=(lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
        if ignore_hup else None)
    return json.loads(out.stdout)


def test_a_closing_terminal_stops_a_process_unless_nohup_asked_it_to_stay() -> None:
    """A review: the SIGHUP handler replaced the SIG_IGN `nohup` had set, and a closing
    terminal stopped `nohup hapticd &`."""
    assert signal.SIGHUP in stops_of_a_process(ignore_hup=False)
    assert signal.SIGHUP not in stops_of_a_process(ignore_hup=True)
    assert {signal.SIGINT, signal.SIGTERM} <= set(stops_of_a_process(ignore_hup=True))
