"""docs/protocol.md's Python example, run as written against a simulated daemon: a client
written from the docs alone copied the example of before, which activated and then waited
for an estimate that never came (it started no exploration)."""

from __future__ import annotations

import contextlib
import io
import re
import threading
from pathlib import Path

from service.daemon.harness import loopback_config, running_node

PROTOCOL = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


def example() -> str:
    text = PROTOCOL.read_text()
    section = text[text.index("## Example (Python"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_protocol_example_follows_an_episode_to_its_end() -> None:
    """An episode longer than the lease's time to live (eggcrate does not converge): the
    example of before never renewed the lease, and a held-out client copying it saw the
    finger stop at step 47 ("deactivated")."""
    code = example()
    assert code.count("tcp://127.0.0.1:5560") == 1 and code.count("tcp://127.0.0.1:5561") == 1
    config = loopback_config({"scenario": {"map": "eggcrate", "max_steps": 100},
                              "lease": {"ttl_s": 1.5}})
    with running_node(config) as node:
        code = (code.replace("tcp://127.0.0.1:5560", node.endpoints["pub"])
                .replace("tcp://127.0.0.1:5561", node.endpoints["cmd"]))
        out, failed = io.StringIO(), []

        def run() -> None:
            try:
                with contextlib.redirect_stdout(out):
                    exec(compile(code, "protocol.md example", "exec"), {})  # noqa: S102
            except Exception as exc:  # reported below, in the test's own thread
                failed.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        thread.join(120)  # an episode of at most 30 steps; a hang is the failure found
        assert not thread.is_alive(), f"the example is still waiting; it printed {out.getvalue()!r}"
    assert not failed, failed
    lines = out.getvalue().splitlines()
    assert "'episode'" in lines[0]  # start_exploration's reply, with its first belief
    assert lines[-1].split()[0] in ("converged", "out_of_steps"), lines[-3:]
