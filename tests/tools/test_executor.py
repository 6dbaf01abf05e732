"""Episodes on an executor: the same results for any number of workers, here or on Dask."""

import json

import pytest

from tools import executor
from tools.cli import main

TIMINGS = ("compute_ms", "policy_ms", "background_ms", "settle_ms")


def without_timings(bench: dict) -> dict:
    for run in bench["runs"]:
        for step in run["steps"]:
            for key in TIMINGS:
                step.pop(key)
    for key in ("summary", "executor", "workers", "cores"):
        bench.pop(key, None)
    return bench


def test_a_pool_of_two_gives_the_results_of_one_worker_bit_for_bit(tmp_path, capsys):
    one, two = tmp_path / "one.json", tmp_path / "two.json"
    common = ["bench", "realistic", "--runs", "4", "--max-steps", "8"]
    assert main([*common, "--workers", "1", "--json", str(one)]) == 0
    assert main([*common, "--workers", "2", "--json", str(two)]) == 0
    out = capsys.readouterr().out
    assert "1 worker (this process)" in out and "local pool of 2 worker processes" in out
    a, b = json.loads(one.read_text()), json.loads(two.read_text())
    assert (a["workers"], b["workers"]) == (1, 2)
    assert without_timings(a) == without_timings(b)


def test_an_unreachable_scheduler_is_a_one_line_error(capsys, monkeypatch):
    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)
    assert main(["bench", "realistic", "--runs", "1", "--scheduler",
                 "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler" in err and err.count("\n") == 1


@pytest.mark.parametrize("args, message", [(["--workers", "0"], "at least 1"),
                                           (["--workers", "2", "--scheduler", "tcp://x:1"],
                                            "own workers")])
def test_bad_executor_options(args, message, capsys):
    assert main(["bench", "realistic", "--runs", "1", *args]) == 2
    assert message in capsys.readouterr().err
