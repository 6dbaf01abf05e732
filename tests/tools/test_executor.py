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


@pytest.mark.parametrize("args, message", [(["--first-seed", "-1"],
                                            "--first-seed -1 with --runs 1 gives seeds outside"),
                                           (["--workers", "2", "--scheduler", "tcp://x:1"],
                                            "own workers")])
def test_bad_executor_options(args, message, capsys):
    assert main(["bench", "realistic", "--runs", "1", *args]) == 2
    assert message in capsys.readouterr().err


def test_a_worker_count_out_of_range_is_refused_as_it_is_parsed(capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "realistic", "--runs", "1", "--workers", "0"])
    assert stopped.value.code == 2
    assert "argument --workers: must be an integer in [1, 256], got '0'" in (
        capsys.readouterr().err)


def test_ctrl_c_inside_a_compiled_kernel_stops_the_run_and_is_no_episodes_error():
    """A held-out check: Ctrl-C (or SIGTERM) that landed while a numba kernel ran came back
    as "SystemError: CPUDispatcher(...) returned a result with an exception set", which the
    episode's guard stored as the episode's error; the campaign ran on to the end and a
    resume never ran that episode again."""

    def interrupted_in_a_kernel(settings, maps):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("CPUDispatcher(<function search>) returned a result with an "
                              "exception set") from exc

    with pytest.raises(KeyboardInterrupt):
        executor.run_one(None, {}, interrupted_in_a_kernel)

    def fails(settings, maps):
        raise SystemError("a fault of the episode's own")

    assert "fault of the episode's own" in executor.run_one(None, {}, fails).error


@pytest.mark.parametrize("address", ["tcp://127.0.0.1", "http://127.0.0.1:8786",
                                     "tcp://127.0.0.1:port", "tcp://127.0.0.1:99999"])
def test_a_malformed_scheduler_address_is_one_line_and_leaves_nothing_behind(address, capfd):
    """It was a clear line, then a 20 s wait and a client's traceback on the way out."""
    assert main(["bench", "realistic", "--runs", "1", "--scheduler", address]) == 2
    err = capfd.readouterr().err
    assert "not a Dask scheduler's address" in err and err.count("\n") == 1, err


def test_a_hands_bench_runs_on_a_dask_cluster():
    """`haptic bench grasp --scheduler` scattered its empty map table and failed inside
    Dask ("not enough values to unpack") every time."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        assert main(["bench", "grasp", "--objects", "keyed", "--hands", "three-finger",
                     "--runs", "1", "--max-steps", "2", "--no-ablation", "--no-single",
                     "--scheduler", cluster.scheduler_address]) == 0


def test_a_scheduler_that_takes_the_connection_and_never_answers_is_a_one_line_error(
        capsys, monkeypatch):
    """A held-out check's listener took the connection and said nothing: the campaign sat
    silent for minutes. It is given up on after the connect timeout and a grace."""
    import socket

    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(executor, "ANSWER_GRACE_S", 1.0)
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        assert main(["bench", "realistic", "--runs", "1", "--scheduler",
                     f"tcp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler" in err and err.count("\n") == 1


class Finished:
    """`distributed.as_completed` over futures that are all done."""

    def __init__(self, futures, ready=True):
        self.futures, self.ready = list(futures), ready

    def is_empty(self):
        return not self.futures

    def has_ready(self):
        return self.ready and bool(self.futures)

    def next_batch(self, block):
        batch, self.futures = self.futures, []
        return batch


def test_a_cluster_left_without_workers_is_a_one_line_error(monkeypatch):
    """A held-out check killed a cluster's only worker: the bench ended in a traceback ("No
    valid workers found") and lost its finished runs; a hand's bench, which scatters no
    map, waited for ever."""
    from service.errors import ServiceError

    class Gone:
        loop = None

        def wait_for_workers(self, n, timeout):
            raise TimeoutError("no worker")

    cluster = executor.DaskCluster.__new__(executor.DaskCluster)
    cluster._client, cluster._futures, cluster.address = Gone(), [], "tcp://x:1"
    with pytest.raises(ServiceError, match=r"has no worker .*2 episodes did not finish: "
                                           r"start a worker"):
        list(cluster.run([0, 1], {}))

    class Empty:
        def scheduler_info(self):
            return {"workers": {}}

    monkeypatch.setattr(executor, "WORKERLESS_S", 0.05)
    monkeypatch.setattr(executor, "POLL_S", 0.01)
    cluster._client = Empty()
    waiting = Finished(["never"], ready=False)
    with pytest.raises(ServiceError, match="has no worker"):
        list(cluster._as_they_finish(waiting, {0: "s"}))


def test_episodes_a_lost_worker_took_along_are_sent_again(monkeypatch, capsys):
    """A held-out check killed a Dask worker mid-bench: the maps scattered to it were lost
    with it, the bench ended in a traceback and kept none of its finished runs. Each
    lost episode is sent again with the maps scattered afresh."""
    import concurrent.futures

    import distributed

    class Future:
        def __init__(self, key, value, lost):
            self.key, self.value, self.lost = key, value, lost

        def result(self):
            if self.lost:
                raise concurrent.futures.CancelledError("lost with its worker")
            return self.value

    class Client:
        loop = None

        def __init__(self):
            self.scattered, self.submitted = 0, []

        def scatter(self, maps, broadcast):
            self.scattered += 1
            return maps

        def submit(self, fn, settings, shared, task, pure):
            self.submitted.append(settings)
            lost = self.scattered == 1 and settings % 2 == 1  # the first round loses odds
            return Future(len(self.submitted), settings * 10, lost)

        def cancel(self, futures):
            pass

        def wait_for_workers(self, n, timeout):
            pass

        def scheduler_info(self):
            return {"workers": {"w": {}}}

    monkeypatch.setattr(distributed, "as_completed", lambda futures, loop: Finished(futures))
    monkeypatch.setattr(executor, "_arrived", lambda outcome, maps: outcome)
    cluster = executor.DaskCluster.__new__(executor.DaskCluster)
    cluster._client, cluster._futures, cluster.address = Client(), [], "tcp://x:1"
    results = dict(cluster.run([0, 1, 2, 3], {"m": object()}))
    assert results == {0: 0, 1: 10, 2: 20, 3: 30}
    assert cluster._client.scattered == 2 and cluster._client.submitted == [0, 1, 2, 3, 1, 3]
    assert "2 episodes are sent again" in capsys.readouterr().err
