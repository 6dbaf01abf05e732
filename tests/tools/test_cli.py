"""The `haptic` command line itself: light start-up, help that teaches, clean exits."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest

from service.daemon.harness import loopback_config, running_node
from service.signals import STOP_SIGNALS
from tools.cli import COMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("numba", "scipy", "matplotlib", "asyncio")
"""Slow to import and not needed by a client (asyncio: 50 ms, through zmq's monitor)."""


def _modules_after(argv: list[str]) -> set[str]:
    """Top-level packages imported by `haptic ARGV` (run in a fresh interpreter)."""
    code = ("import json, sys\nfrom tools.cli import main\ntry:\n    main(sys.argv[1:])\n"
            "except SystemExit:\n    pass\n"
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))")
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)
    return set(json.loads(proc.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("argv", [
    ["--help"], ["ctl", "--help"], ["watch", "--help"], ["explore", "--help"],
    ["ctl", "status", "--cmd", "tcp://127.0.0.1:1", "--timeout", "0.05", "--retries", "0"],
    ["watch", "--pub", "tcp://127.0.0.1:1", "--duration", "0.05"],
])
def test_operator_commands_import_no_numerics(argv: list[str]) -> None:
    loaded = _modules_after(argv)
    assert "zmq" in loaded or argv == ["--help"]  # it did get as far as the command
    assert not loaded & set(HEAVY), f"haptic {' '.join(argv)} imported {loaded & set(HEAVY)}"


def _all_helps() -> dict[str, str]:
    """Every command's (and sub-verb's) help text, parser by parser."""
    texts: dict[str, str] = {}

    def walk(parser, name: str) -> None:
        texts[name] = parser.format_help()
        for action in parser._actions:
            if hasattr(action, "register_all"):
                action.register_all()
                for sub, p in action.choices.items():
                    walk(p, f"{name} {sub}".strip())

    walk(build_parser(), "")
    return texts


def test_every_command_is_listed_and_described() -> None:
    helps = _all_helps()
    top = helps[""]
    for name, (_, summary) in COMMANDS.items():
        assert name in top and summary.split()[0] in top
    for name, text in helps.items():
        if name:
            description = text.split("\n\n")[1]
            assert len(description.split()) >= 4, f"haptic {name} has no description"


def test_no_help_shows_a_default_of_none() -> None:
    for name, text in _all_helps().items():
        assert "default: None" not in text, f"haptic {name} --help shows 'default: None'"


def test_a_benchmark_that_always_has_noise_says_so_of_its_noise_option() -> None:
    """`haptic bench realistic --help` said --noise would "turn on" B2's noise, which those
    benchmarks always run with (a held-out check ran both and got the same numbers)."""
    helps = {name: " ".join(text.split()) for name, text in _all_helps().items()}
    for name in ("bench realistic", "bench scale", "bench objects", "bench profile"):
        assert "--noise always on here" in helps[name], name
    for name in ("run", "bench paper"):
        assert "--noise turn on BENCHMARKS.md B2's noise" in helps[name], name


def test_ctl_help_lists_the_commands_and_their_arguments(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["ctl", "--help"])
    out = capsys.readouterr().out
    assert "set_map map=STR [spacing=NUMBER]" in out
    assert "start_exploration [repeat=BOOL]" in out and "estop [reason=STR]" in out


def test_a_user_error_is_one_line_with_status_2(capsys) -> None:
    assert main(["ctl", "configure", "oops", "--cmd", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not KEY=VALUE" in err


@pytest.mark.parametrize("argv, words", [
    (["run", "--seed", "abc"], "haptic run: error: argument --seed: invalid int value: 'abc'"),
    (["bench", "grasp", "--runs", "x"], "haptic bench grasp: error: argument --runs"),
    (["ctl", "--timeout", "1"],  # KEY=VALUE was called required too
     "haptic ctl: error: the following arguments are required: COMMAND ("),
])
def test_a_bad_option_is_one_line_naming_the_help(capsys, argv: list[str], words: str) -> None:
    """argparse printed its usage block first (a bad type, e.g. `--seed abc`)."""
    with pytest.raises(SystemExit) as end:
        main(argv)
    err = capsys.readouterr().err
    assert end.value.code == 2 and err.count("\n") == 1 and err.startswith(words), err
    assert f"`haptic {' '.join(argv[:-2])} --help` lists the options" in err


def _catches(pid: int, sig: int) -> bool:
    """Whether process `pid` has a handler installed for `sig` (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (sig - 1) & 1)
    return False


def _start_in_background(argv: list[str]) -> subprocess.Popen:
    """As a non-interactive shell starts `cmd &`: SIGINT ignored. Waits for the handlers."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", *argv], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    deadline = time.monotonic() + 30
    while not all(_catches(proc.pid, sig) for sig in STOP_SIGNALS):
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)  # polling /proc for readiness, not waiting for a result
    return proc


@pytest.mark.parametrize("sig", STOP_SIGNALS)
def test_watch_in_the_background_ends_cleanly_on_a_signal(sig: int) -> None:
    """SIGHUP too: a closing terminal sends it, and by its default a held-out check's
    `haptic run --backend dynamixel` died at once with its servos' torque on."""
    with running_node(loopback_config()) as node:
        proc = _start_in_background(["watch", "--pub", node.endpoints["pub"], "--topics",
                                     "state"])
        assert proc.stdout.readline().startswith("state")  # it is in its loop
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0
    assert "Traceback" not in err and " messages, " in err


def test_a_signal_during_start_up_is_a_clean_interruption() -> None:
    proc = _start_in_background(["watch", "--pub", "tcp://127.0.0.1:1"])
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode in (0, 128 + signal.SIGTERM)  # in its loop already, or not yet
    assert "Traceback" not in err


def test_a_signal_while_the_command_sets_up_is_a_clean_interruption(monkeypatch, capsys
                                                                   ) -> None:
    """SIGTERM landing after the handlers are in but before the command's own set-up ends
    (a background `watch` killed at once: exit 1 with a traceback, once in 60 tries)."""
    from contextlib import contextmanager

    import tools.cli as cli
    from tools.signals import _on_signal

    @contextmanager
    def interrupted_set_up():
        _on_signal(signal.SIGTERM, None)  # what the handler does as the signal lands
        yield

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli, "_one_blas_thread", interrupted_set_up)
    assert main(["watch", "--pub", "tcp://127.0.0.1:1"]) == 128 + signal.SIGTERM
    assert "haptic watch: interrupted" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the drop
def test_a_signal_whose_exception_python_drops_still_ends_a_watch(monkeypatch) -> None:
    """Raised while Python runs a __del__ or a weakref callback (an import's lock clean-up),
    the handler's exception is printed and dropped: the watch must end all the same (it ran
    on after `kill`, once in ~500 tries)."""
    from service.wire.client import Subscriber
    from tools.signals import _on_signal

    class LandsInADestructor:
        def __del__(self) -> None:
            _on_signal(signal.SIGTERM, None)

    calls = []

    def recv(self, timeout=None):
        calls.append(timeout)
        assert len(calls) < 5, "the watch went on after its signal"
        LandsInADestructor()  # the signal lands; Python drops its exception
        return None

    monkeypatch.setattr(Subscriber, "recv", recv)
    assert main(["watch", "--pub", "tcp://127.0.0.1:1"]) == 0
    assert len(calls) == 1


def test_a_closed_pipe_ends_quietly(tmp_path: Path) -> None:
    from service.wire import envelope as wire

    rec = tmp_path / "many.hrec"
    with rec.open("wb") as f:
        f.write(msgpack.packb({"format": "haptic-record", "v": 1, "config": None}))
        for i in range(1, 20001):
            payload = wire.encode("event", i, {"event": "lifecycle", "state": "inactive"})
            f.write(msgpack.packb({"topic": "event", "t_ns": i, "payload": payload}))
    proc = subprocess.run(f"'{sys.executable}' -m tools.cli replay '{rec}' | head -2",
                          shell=True, cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.stdout.count("\n") == 2
    assert proc.stderr == ""


def test_ctrl_c_during_a_bus_exchange_waits_for_it_and_ends_cleanly(monkeypatch, capsys):
    """The interrupt lands mid-exchange; the exchange completes (no half packet on the bus,
    no bogus bus error), then the command ends as interrupted."""
    from types import SimpleNamespace

    from firmware_if.hand import load_hand
    from tools import bus_cli

    hand = load_hand("spatial")
    exchanges: list[str] = []

    class Bus:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def detect_fast_read(self):
            return True

        def cycle(self):
            exchanges.append("sent")
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the reply is awaited
            sum(range(10_000))  # bytecodes: where an unheld interrupt would strike
            exchanges.append("answered")
            return {j.id: SimpleNamespace(position=2048) for j in hand.joints}

    monkeypatch.setattr(bus_cli, "_bus", lambda args, hand: Bus())
    assert main(["bus", "read", "--port", "/dev/null", "--hand", "spatial"]) == 130
    assert exchanges == ["sent", "answered"]
    assert capsys.readouterr().err.strip() == "haptic bus read: interrupted"


def test_a_start_with_a_minus_or_many_turns_is_taken_as_typed(tmp_path, capsys):
    """A held-out researcher's `--start -0.01,0.05,0` was "expected one argument" (argparse
    took it for an option), and `--start 0.1,0.05,60000` was refused in radians it never
    typed ("got (0.1, 0.05, 1047.19...)")."""
    assert main(["run", "--start", "-0.01,0.05,0", "--max-steps", "1", "--quiet"]) == 2
    assert "start (-0.01, 0.05) m" in capsys.readouterr().err  # read, then found off the map
    out = tmp_path / "run.json"
    assert main(["run", "--start", "0.1,0.05,60000", "--max-steps", "1", "--quiet",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["truth"]["heading"] == pytest.approx(
        math.radians(60000 % 360))


@pytest.mark.parametrize("argv, said, status", [
    # a held-out check of bad input: each was a traceback
    (["view", "--png", "/nonexistent/x.png"], "folder /nonexistent does not exist", 2),
    (["emulate", "--hand", "planar", "--link", "/nonexistent/dir/x"],
     "folder /nonexistent/dir does not exist", 2),
    (["run", "--max-steps", "2", "--quiet", "--json", "/dev/full"],
     "cannot write: No space left on device", 1),
])
def test_an_output_that_cannot_be_written_is_one_line(argv, said, status, capsys):
    assert main(argv) == status
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0]


@pytest.mark.parametrize("argv, said", [
    (["run", "--frobnicate", "3"], "haptic run: error: unrecognized arguments: --frobnicate 3 "
                                   "(`haptic run --help` lists the options)"),
    (["bench", "paper", "--frob"], "haptic bench paper: error: unrecognized arguments: --frob"),
])
def test_an_unknown_option_is_the_commands_one_line(argv, said, capsys):
    """A held-out check: `haptic run --frobnicate 3` printed the top level's usage and
    "haptic: error: ...", where every other refusal is the command's one line."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(said)


@pytest.mark.parametrize("argv, said", [
    # a held-out check: each ran as if the option had not been given
    (["run", "--mu", "0.9", "--no-gate"], "--no-gate, --mu apply to a hand holding an object"),
    (["run", "--plane", "z=0"], "--plane applies to a hand holding an object"),
    (["run", "--port", "/dev/ttyUSB0"], "--port is a servo bus's: it needs --backend"),
    (["emulate", "--hand", "two-finger", "--object", "blob", "--map", "bumps"],
     "--map belongs to a finger's map; a hand holding --object has none"),
    (["run", "--noise", "--headings", "72"], "--headings shapes the pose table"),
    (["run", "--start", "0.1,0.1,0", "--headings", "12"], "--headings shapes the pose table"),
    (["bench", "realistic", "--headings", "5"], "--headings shapes the pose table"),
])
def test_an_option_that_would_be_ignored_is_refused(argv, said, capsys):
    assert main(argv) == 2
    assert said in capsys.readouterr().err
