"""The README's commands, run exactly as written (copied out of README.md at test time)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def readme_block(heading: str) -> str:
    """The first ```sh block after `heading` in README.md."""
    section = (ROOT / "README.md").read_text().split(heading, 1)[1]
    return section.split("```sh\n", 1)[1].split("```", 1)[0]


def endpoints() -> dict[str, str]:
    """HAPTIC_PUB and HAPTIC_CMD on two loopback ports free now, and not the same one (each
    port is held until both are chosen; a helper's hunt saw the two could coincide)."""
    with socket.socket() as pub, socket.socket() as cmd:
        pub.bind(("127.0.0.1", 0))
        cmd.bind(("127.0.0.1", 0))
        return {"HAPTIC_PUB": f"tcp://127.0.0.1:{pub.getsockname()[1]}",
                "HAPTIC_CMD": f"tcp://127.0.0.1:{cmd.getsockname()[1]}"}


@contextmanager
def busy_cores() -> Iterator[None]:
    """At least as many runnable processes as cores (spinning ones added if the load is
    lower): the busy machine the README must work on."""
    spare = (os.cpu_count() or 2) - int(os.getloadavg()[0])
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(max(0, spare))]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def _gone(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    return False


def run_block(script: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """The block as one `bash -e` script; afterwards nothing it started is left running."""
    proc = subprocess.Popen(["bash", "-e", "-c", script], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        deadline = time.monotonic() + 30
        while not _gone(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.05)  # `kill %1` asked the daemon to stop: let it finish
        if not _gone(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise AssertionError("the README's daemon did not stop after `kill %1`")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_the_daemon_section_works_as_written_three_times_on_a_busy_machine(tmp_path):
    script = readme_block("## The service: `hapticd`")
    assert ".venv/bin/haptic explore" in script and "kill %1" in script
    assert "haptic record run.mcap" in script and "haptic export run.mcap" in script
    (tmp_path / ".venv").symlink_to(ROOT / ".venv")  # a fresh clone's folder, after make
    env = {**os.environ, **endpoints(), "MPLBACKEND": "Agg"}
    with busy_cores():
        for attempt in range(3):
            done = run_block(script, tmp_path, env)
            log = (tmp_path / "hapticd.log").read_text()
            assert done.returncode == 0, (attempt, done.stdout, done.stderr, log[-2000:])
            assert "result    localized in" in done.stdout
            assert '"state": "inactive"' in done.stdout  # ctl status, after explore
            assert (tmp_path / "view.png").read_bytes()[:4] == b"\x89PNG"
            assert '"event": "shutdown"' in log
            (episode,) = json.loads((tmp_path / "episodes.json").read_text())
            assert episode["converged"] and episode["success"] and episode["steps"]
            for made in ("view.png", "run.mcap", "episodes.json", "hapticd.log"):
                (tmp_path / made).unlink()


def test_the_hand_under_hapticd_section_works_as_written(tmp_path):
    script = readme_block("### A hand under `hapticd`")
    assert "config/hand.toml" in script and "kill %1" in script
    (tmp_path / ".venv").symlink_to(ROOT / ".venv")
    (tmp_path / "config").symlink_to(ROOT / "config")
    env = {**os.environ, **endpoints()}
    done = run_block(script, tmp_path, env)
    log = (tmp_path / "hapticd.log").read_text()
    assert done.returncode == 0, (done.stdout, done.stderr, log[-2000:])
    assert "finger 0 rolls" in done.stdout and "result    localized in" in done.stdout
    assert "fingers 0: (" in done.stdout and "; 2: (" in done.stdout  # all three fingers
    assert '"event": "shutdown"' in log


def test_the_hand_file_example_loads_and_a_misspelt_key_is_named(tmp_path):
    """A held-out client's writer found the hand file undocumented and copied a preset; the
    README's example is a hand file as written."""
    from firmware_if.errors import HandConfigError
    from firmware_if.hand import load_hand

    section = (ROOT / "README.md").read_text().split("**Your own hand file**", 1)[1]
    example = section.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "my-hand.toml").write_text(example)
    hand = load_hand(str(tmp_path / "my-hand.toml"))
    assert hand.name == "my-hand" and hand.ids == (1, 2, 3) and hand.fingers[0].planar
    (tmp_path / "bad.toml").write_text(example.replace("limits = [0.1", "limit = [0.1"))
    try:
        load_hand(str(tmp_path / "bad.toml"))
    except HandConfigError as exc:
        assert "finger 'left'" in str(exc) and "'limit'" in str(exc)
    else:
        raise AssertionError("a misspelt key loaded")
