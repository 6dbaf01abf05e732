"""`haptic emulate`, `haptic bus scan|read|check` and the bus benchmark, on the emulator."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from tools import bench_bus, cli, emulate_cli


@pytest.fixture
def emulated(capsys):
    """(port, what `haptic emulate` printed) of an emulator running in a thread."""
    args = cli.build_parser().parse_args(["emulate", "--hand", "spatial", "--seed", "3"])
    ready, stop = threading.Event(), threading.Event()
    box: dict[str, str] = {}

    def on_ready(port: str) -> None:
        box["port"] = port
        ready.set()

    thread = threading.Thread(target=emulate_cli.run, args=(args,),
                              kwargs={"ready": on_ready, "stop": stop})
    thread.start()
    assert ready.wait(10)
    yield box["port"], capsys.readouterr().out
    stop.set()
    thread.join(10)
    assert not thread.is_alive()


def test_emulate_prints_the_port_and_the_truth_of_the_seed(emulated):
    port, out = emulated
    assert out.splitlines()[0] == port
    assert "x=0.1200 m, y=0.1000 m" in out  # what `haptic run --seed 3` draws


def test_bus_scan_read_check(emulated, capsys):
    emulated_port, _ = emulated
    assert cli.main(["bus", "scan", "--port", emulated_port]) == 0
    out = capsys.readouterr().out
    assert [line.split(":")[0] for line in out.splitlines()] == [
        "id   1", "id   2", "id   3", "id   4"]
    assert "XM430-W350, firmware 46" in out
    assert cli.main(["bus", "read", "--port", emulated_port, "--hand", "spatial", "--count",
                     "2", "--interval", "0"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()  # a cycle missed under load is a line on stderr
    assert len(lines) + captured.err.count("missed") == 2 and "centre x=" in lines[0]
    assert cli.main(["bus", "check", "--port", emulated_port, "--hand", "spatial"]) == 0
    out = capsys.readouterr().out
    assert "no USB latency timer" in out
    assert "warn servo 1: operating mode 3 (position)" in out
    assert all(f"ok   servo {sid}: torque off" in out for sid in (1, 2, 3, 4))
    assert "FAIL" not in out


def test_bus_release_turns_off_the_torque_a_killed_driver_left_on(emulated, capsys):
    """A daemon killed outright (SIGKILL) leaves its servos holding their goal with torque
    on; `bus check` says so, and nothing in the tools turned it off."""
    from firmware_if.dxl_bus import DxlBus

    port, _ = emulated
    driver = DxlBus(port, (1, 2, 3, 4))
    driver.open()
    driver.torque(True)
    driver._port.closePort()  # killed: the kernel closes the port, and nothing else happens
    assert cli.main(["bus", "check", "--port", port, "--hand", "spatial"]) == 0
    assert "warn servo 3: torque on, though nothing drives it" in capsys.readouterr().out
    assert cli.main(["bus", "release", "--port", port, "--hand", "planar"]) == 0
    captured = capsys.readouterr()  # a smaller hand's release left 3 and 4 on, unsaid
    assert captured.out.splitlines() == ["servo 1: torque off", "servo 2: torque off"]
    assert "servo 3, 4 also answered, which hand 'planar' does not use" in captured.err
    assert cli.main(["bus", "release", "--port", port]) == 0
    captured = capsys.readouterr()
    assert captured.out.splitlines() == [f"servo {sid}: torque off" for sid in (1, 2, 3, 4)]
    assert "one that did not (muted, unpowered) was not released" in captured.err
    assert cli.main(["bus", "check", "--port", port, "--hand", "spatial"]) == 0
    out = capsys.readouterr().out
    assert all(f"ok   servo {sid}: torque off" in out for sid in (1, 2, 3, 4))


def test_bus_check_fails_on_a_wrong_baud_register(emulated, capsys, tmp_path):
    emulated_port, _ = emulated
    hand = tmp_path / "slow.toml"
    from firmware_if.hand import PRESET_DIR

    hand.write_text((PRESET_DIR / "spatial.toml").read_text().replace(
        "baud = 1000000", "baud = 57600"))
    assert cli.main(["bus", "check", "--port", emulated_port, "--hand", str(hand),
                     "--baud", "1000000"]) == 1
    assert "FAIL servo 1: baud register 3 (1000000 bps) but the hand says 57600" in \
        capsys.readouterr().out


def test_bus_read_reports_a_missed_cycle_and_goes_on(emulated, capsys, monkeypatch):
    """A reply that misses its window (a loaded host) is one line on stderr, not the end
    of `haptic bus read` (it ended with an error in make test under load)."""
    from firmware_if.dxl_bus import DxlBus
    from firmware_if.errors import BusTimeoutError

    port, _ = emulated
    real, calls = DxlBus.cycle, []

    def misses_the_first(self, goals=None):
        calls.append(goals)
        if len(calls) == 1:
            raise BusTimeoutError("fast sync read: [TxRxResult] There is no status packet!",
                                  (1,))
        return real(self, goals)

    monkeypatch.setattr(DxlBus, "cycle", misses_the_first)
    assert cli.main(["bus", "read", "--port", port, "--hand", "spatial", "--count", "3",
                     "--interval", "0"]) == 0
    captured = capsys.readouterr()
    assert "# cycle 1 missed: fast sync read" in captured.err
    assert len([line for line in captured.out.splitlines() if "centre" in line]) == 2


def test_bench_bus_measures_and_writes_json(tmp_path, capsys):
    result = bench_bus.measure(servos=3, cycles=50)
    # missed cycles are the host's load: counted, not fatal
    assert result["read"] == "fast sync read" and 0 <= result["failures"] < result["cycles"]
    assert 0 < result["p50_ms"] <= result["p99_ms"] <= result["max_ms"]
    parser = argparse.ArgumentParser()
    bench_bus.add_arguments(parser)
    out = tmp_path / "bus.json"
    assert bench_bus.run(parser.parse_args(["--cycles", "30", "--json", str(out)])) == 0
    data = json.loads(out.read_text())
    assert [r["read"] for r in data["results"]] == ["fast sync read", "sync read"]


def test_a_drill_typed_into_emulate_faults_the_backend(capsys):
    """`haptic emulate` reads fault drills on its standard input: a reboot typed there is a
    brown-out the backend must notice (a fault campaign had to wrap the emulator for it)."""
    from firmware_if.dynamixel_backend import DynamixelBackend, StepSettings
    from firmware_if.hand import load_hand

    args = cli.build_parser().parse_args(["emulate", "--hand", "spatial", "--seed", "3"])
    read_end, write_end = os.pipe()
    ready, stop = threading.Event(), threading.Event()
    box: dict[str, str] = {}

    def on_ready(port: str) -> None:
        box["port"] = port
        ready.set()

    with os.fdopen(read_end) as drills, os.fdopen(write_end, "w") as typed:
        thread = threading.Thread(target=emulate_cli.run, args=(args,), kwargs={
            "ready": on_ready, "stop": stop, "drills": drills})
        thread.start()
        try:
            assert ready.wait(10)
            backend = DynamixelBackend(load_hand("spatial"), box["port"],
                                       StepSettings(cycle_budget_s=0.1))
            backend.open()
            try:
                backend.set_torque(True)
                typed.write("reboot 9\nreboot 2\n")
                typed.flush()
                for _ in range(200):
                    state = backend.read_state()
                    if state.fault:
                        break
                assert state.fault and "servo 2 lost torque" in state.fault
            finally:
                backend.close()
        finally:
            stop.set()
            thread.join(10)
    out = capsys.readouterr().out
    assert "drill refused: no servo 9 on this bus" in out and "ok: reboot 2" in out


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO here")
def test_the_emulator_answers_from_a_real_time_thread_or_says_why_not():
    """Starved on a loaded machine, an ordinary emulator answered late enough to fault an
    idle bus: `haptic emulate` asks for SCHED_FIFO above hapticd's loop."""
    from sim_backend.emulator import EmulatedServo, ServoBus

    with ServoBus([EmulatedServo(1)], priority=emulate_cli.EMULATOR_PRIORITY) as bus:
        policy = os.sched_getscheduler(bus._thread.native_id) & ~getattr(
            os, "SCHED_RESET_ON_FORK", 0)
        got = bus.scheduling
        if got.policy == "fifo":
            assert policy == os.SCHED_FIFO and got.priority == emulate_cli.EMULATOR_PRIORITY
        else:
            assert policy == os.SCHED_OTHER and "--priority 0" in got.note
    with ServoBus([EmulatedServo(1)]) as bus:  # tests and benches: ordinary
        assert bus.scheduling is None
        assert os.sched_getscheduler(bus._thread.native_id) == os.SCHED_OTHER


def test_emulate_says_when_its_priority_is_refused(monkeypatch, capsys):
    from service.daemon import priority

    def refuse(pid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    args = cli.build_parser().parse_args(["emulate", "--hand", "spatial", "--seed", "3"])
    stop = threading.Event()
    stop.set()  # serve until asked: at once
    assert emulate_cli.run(args, stop=stop) == 0
    err = capsys.readouterr().err
    assert "note: SCHED_FIFO 30 refused (Operation not permitted): the emulated servos" in err


ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(shutil.which("script") is None, reason="no script(1) for a terminal")
def test_emulate_started_with_an_ampersand_in_an_interactive_shell_serves(tmp_path):
    """The README starts the emulator with `&`. In an interactive shell its read of the
    terminal for drills stopped it (SIGTTIN, "Stopped (tty input)") and `haptic bus scan`
    found no servo on its port (a held-out check). A shell in a terminal of its own
    (script(1)) starts it in the background, waits for its port, and scans it."""
    link, haptic = tmp_path / "dxl", f"{shlex.quote(sys.executable)} -m tools.cli"
    (tmp_path / "session.sh").write_text(f"""cd {shlex.quote(str(ROOT))}
{haptic} emulate --hand two-finger --object keyed --seed 2 --link {link} > /dev/null &
for i in $(seq 200); do [ -e {link} ] && break; sleep 0.1; done
{haptic} bus scan --port {link} 2>&1
kill %1; kill -CONT %1 2>/dev/null
wait
exit
""")
    done = subprocess.run(["script", "-qfec", f"bash --norc -i {tmp_path / 'session.sh'}",
                           "/dev/null"], capture_output=True, text=True, timeout=120,
                          stdin=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert "Stopped" not in done.stdout, done.stdout
    assert "id   1:" in done.stdout and "id   6:" in done.stdout, done.stdout


def test_a_second_run_on_one_emulator_is_scored_where_it_began(emulated, tmp_path):
    """A held-out check: the second `haptic run --seed 3` on one emulator began where the
    first had left the finger, was scored against the seed's start, and said "WRONG: ...
    42.3 mm away" (exit 1) of a right pose. The truth is now the seed's start moved by the
    finger's offset from its home posture, as the emulator places it."""
    port, _ = emulated
    runs = []
    for k in range(2):
        out = tmp_path / f"run{k}.json"
        assert cli.main(["run", "--backend", "dynamixel", "--port", port, "--hand", "spatial",
                         "--seed", "3", "--max-steps", "30", "--quiet", "--cycle-budget",
                         "50", "--json", str(out)]) == 0
        runs.append(json.loads(out.read_text()))
    assert all(run["success"] for run in runs)
    first, second = (np.array([r["truth"]["x"], r["truth"]["y"]]) for r in runs)
    assert np.hypot(*(first - (0.12, 0.10))) < 0.001  # a fresh emulator: the seed's start
    assert np.hypot(*(second - first)) > 0.01  # the second began where the first ended
