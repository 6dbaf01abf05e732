"""Where benchmark episodes run: here, on a local pool of processes, or on a Dask cluster.

An episode is a pure function of its settings (seed included) and its map, so it may run
in any process and in any order: results come back as they finish and are put back in
order, and they are the same, bit for bit apart from timings, for any number of workers
(`tests/tools/test_executor.py`). Compute per step is timed inside each episode; when
several workers share a machine they contend for its cores, so every report says how many
did (`Executor.describe`).

Maps travel once per worker (the pool's initializer, Dask's `scatter`), not once per
episode; a finished episode travels back without its map and is given it again here.
An episode is a finger's on a map (`on_map`) unless the caller names another task, a
module-level function of (settings, maps) (a hand's: `haptic bench grasp`).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from service.episode.scenario import RunSettings
from service.episode.simulate import EpisodeReport, simulate
from service.errors import ConfigError, InputError, ServiceError
from service.localization.surface import HeightMap
from tools.arg_types import integer

CONNECT_TIMEOUT_S = 10.0
"""How long to try reaching a Dask scheduler."""
ANSWER_GRACE_S = 5.0
"""How much longer than `CONNECT_TIMEOUT_S` a peer that took the connection may take to
answer as a scheduler."""
LOST_RETRIES = 3
"""Times the episodes a lost Dask worker took with it are sent again."""
WORKERLESS_S = 20.0
"""How long a Dask cluster may have no worker before the episodes left are given up on."""
POLL_S = 0.2
"""How often a run on Dask with nothing finished looks whether any worker is left."""
PRELOAD = ["service.episode.simulate", "service.localization.kernels",
           "service.localization.localizers.particles", "tools.executor",
           "tools.executor_warm"]
"""Imported once by the pool's fork server, so each worker starts warm."""


@dataclass(frozen=True)
class Failed:
    """An episode that raised instead of finishing (a benchmark reports it and goes on)."""

    settings: Any
    """What the episode was asked to run (RunSettings, or a task's own settings)."""
    error: str
    refused: bool = False
    """It refused its settings (an `InputError`): a user's to fix, not a fault of the run."""

    def to_json(self) -> dict[str, Any]:
        return {"settings": self.settings.to_json(), "error": self.error}


Outcome = EpisodeReport | Failed | Any
Task = Callable[[Any, dict[str, HeightMap]], Any]
"""One episode from its settings and the shared maps, in whichever process runs it."""


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def on_map(settings: RunSettings, maps: dict[str, HeightMap]) -> EpisodeReport:
    """A finger's episode on its map: the default task."""
    return simulate(settings, maps[settings.map])


def run_one(settings: Any, maps: dict[str, HeightMap], task: Task = on_map) -> Outcome:
    """One episode, in whichever process runs it; an exception becomes `Failed`."""
    _one_thread()
    try:
        return task(settings, maps)
    except Exception as exc:  # noqa: BLE001 - reported per episode, the rest go on
        interrupt = _interrupt_behind(exc)
        if interrupt is not None:
            raise interrupt from None
        first = str(exc).splitlines()[0] if str(exc) else ""
        return Failed(settings, f"{type(exc).__name__}: {first}", isinstance(exc, InputError))


def _interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM (`tools.signals`) an exception stands for, if any. One that
    lands while a compiled kernel runs comes back as a SystemError ("... returned a result
    with an exception set") caused by it: taken for the episode's own error, it was stored
    as one, which a resumed campaign never ran again, and the run went on."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def _portable(outcome: Outcome) -> Outcome:
    """What crosses a process boundary: a report without its map (given back on arrival)."""
    if isinstance(outcome, EpisodeReport):
        return dataclasses.replace(outcome, height_map=None, snapshots={})  # type: ignore
    return outcome


def _arrived(outcome: Outcome, maps: dict[str, HeightMap]) -> Outcome:
    if isinstance(outcome, EpisodeReport):
        return dataclasses.replace(outcome, height_map=maps[outcome.settings.map])
    return outcome


_threads_limited = False


def _one_thread() -> None:
    """One BLAS thread per worker, as in `haptic` itself (and the same arithmetic)."""
    global _threads_limited
    if not _threads_limited:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
        _threads_limited = True


class Executor(ABC):
    """Runs episodes; yields (index, outcome) as each finishes."""

    workers: int

    @abstractmethod
    def describe(self) -> str:
        """Where the episodes ran and who shared the machine, for reports."""

    @abstractmethod
    def run(self, settings: Sequence[Any], maps: dict[str, HeightMap],
            task: Task = on_map) -> Iterator[tuple[int, Outcome]]: ...

    def info(self) -> dict[str, Any]:
        return {"executor": self.describe(), "workers": self.workers, "cores": cores()}

    @abstractmethod
    def close(self) -> None:
        """Release workers and connections."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class InProcess(Executor):
    """Episodes one after another in this process: the timing reference (one worker)."""

    workers = 1

    def describe(self) -> str:
        return f"1 worker (this process) on a machine with {cores()} cores"

    def run(self, settings, maps, task=on_map):
        for i, s in enumerate(settings):
            yield i, run_one(s, maps, task)

    def close(self) -> None:
        """Nothing to release."""


_pool_maps: dict[str, HeightMap] = {}


def _pool_start(maps: dict[str, HeightMap]) -> None:
    """A pool worker's setup: keep the maps; Ctrl-C is the parent's to handle."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _pool_maps.update(maps)
    _one_thread()


def _pool_task(item: tuple[int, Any, Task]) -> tuple[int, Outcome]:
    index, settings, task = item
    return index, _portable(run_one(settings, _pool_maps, task))


class LocalPool(Executor):
    """A pool of `workers` processes on this machine, forked from a warm fork server."""

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self.workers = workers
        self._context = multiprocessing.get_context("forkserver")
        self._context.set_forkserver_preload(PRELOAD)
        self._pool: Any = None

    def describe(self) -> str:
        return (f"a local pool of {self.workers} worker processes sharing a machine with "
                f"{cores()} cores")

    def run(self, settings, maps, task=on_map):
        self._pool = self._context.Pool(self.workers, initializer=_pool_start,
                                        initargs=(maps,))
        try:
            items = [(i, s, task) for i, s in enumerate(settings)]
            for index, outcome in self._pool.imap_unordered(_pool_task, items):
                yield index, _arrived(outcome, maps)
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()  # an interrupted run leaves nothing running
            self._pool.join()
            self._pool = None


def _dask_task(settings: Any, maps: dict[str, HeightMap], task: Task) -> Outcome:
    return _portable(run_one(settings, maps, task))


class DaskCluster(Executor):
    """An existing Dask distributed cluster, reached at its scheduler's address."""

    def __init__(self, address: str) -> None:
        from distributed import Client

        _check_address(address)
        self._client = _connect(Client, address)
        self.address = address
        self.workers = max(1, len(self._client.scheduler_info().get("workers", {})))
        self._futures: list[Any] = []

    def describe(self) -> str:
        return f"the Dask cluster at {self.address} ({self.workers} workers)"

    def run(self, settings, maps, task=on_map):
        """The episodes as they finish. A worker lost takes its episodes and the maps
        scattered to it along: those are sent again with the maps scattered afresh, at
        most `LOST_RETRIES` times (a held-out check killed a worker: the bench ended in a
        traceback and kept none of its finished runs)."""
        from concurrent.futures import CancelledError

        from distributed import KilledWorker, as_completed

        pending = dict(enumerate(settings))
        for attempt in range(LOST_RETRIES + 1):
            if attempt:
                print(f"the Dask cluster lost a worker: {len(pending)} episodes are sent "
                      "again", file=sys.stderr)
            self._await_a_worker(len(pending))
            # a hand's episodes share no map (scattering nothing fails inside Dask)
            try:
                shared = self._client.scatter(maps, broadcast=True) if maps else {}
            except Exception as exc:  # its last worker went meanwhile: "No valid workers"
                raise self._workerless(len(pending), _first_line(exc)) from None
            index = {}
            for i, s in pending.items():
                future = self._client.submit(_dask_task, s, shared, task, pure=False)
                index[future.key] = i
                self._futures.append(future)
            try:
                for future in self._as_they_finish(as_completed(self._futures,
                                                                loop=self._client.loop),
                                                   pending):
                    try:
                        outcome = future.result()
                    except (CancelledError, KilledWorker):  # lost with a worker
                        continue
                    except Exception as exc:  # the cluster's, not the episode's (caught there)
                        raise ServiceError(f"the Dask cluster at {self.address} failed an "
                                           f"episode: {_first_line(exc)}") from None
                    i = index[future.key]
                    del pending[i]
                    yield i, _arrived(outcome, maps)
            finally:
                self._client.cancel(self._futures)
                self._futures = []
            if not pending:
                return
        raise ServiceError(f"the Dask cluster at {self.address} lost workers "
                           f"{LOST_RETRIES + 1} times; {len(pending)} episodes did not "
                           "finish: check its workers and run the same command again")

    def _as_they_finish(self, finished: Any, pending: dict) -> Iterator[Any]:
        """The futures of `finished` (an `as_completed`) as they finish, giving up when the
        cluster has had no worker for `WORKERLESS_S`: episodes that need no map wait for a
        worker for ever (a held-out check's bench hung when the last worker died)."""
        idle_since: float | None = None
        while not finished.is_empty():
            if finished.has_ready():
                idle_since = None
                yield from finished.next_batch(block=False)
                continue
            if self._has_workers():
                idle_since = None
            elif idle_since is None:
                idle_since = time.monotonic()
            elif time.monotonic() - idle_since > WORKERLESS_S:
                raise self._workerless(len(pending), f"none for {WORKERLESS_S:g} s")
            time.sleep(POLL_S)  # a poll of the cluster, not a wait for an event of ours

    def _await_a_worker(self, left: int) -> None:
        try:
            self._client.wait_for_workers(1, timeout=WORKERLESS_S)
        except Exception:  # TimeoutError, or the scheduler gone
            raise self._workerless(left, f"none for {WORKERLESS_S:g} s") from None

    def _has_workers(self) -> bool:
        try:
            return bool(self._client.scheduler_info().get("workers"))
        except Exception:  # the scheduler gone: no worker of its either
            return False

    def _workerless(self, left: int, why: str) -> ServiceError:
        """A one-line error for a cluster left with no worker (a traceback, "No valid
        workers found", ended a held-out check's campaign when its last worker died)."""
        return ServiceError(f"the Dask cluster at {self.address} has no worker ({why}); "
                            f"{left} episodes did not finish: start a worker (`dask worker "
                            f"{self.address}`) and run the same command again")

    def close(self) -> None:
        self._client.close()


def _connect(client_class: Any, address: str) -> Any:
    """A Dask client of the scheduler at `address`, or a one-line ConfigError. The client
    is made on a thread and waited for: a peer that took the connection and never
    answered held a campaign silent for minutes, and another's answer ended in a
    traceback (an allocation of 3 EiB)."""
    import threading

    made: dict[str, Any] = {}

    def connect() -> None:
        try:
            made["client"] = client_class(address, timeout=f"{CONNECT_TIMEOUT_S}s",
                                          set_as_default=False)
        except Exception as exc:  # whatever the peer made Dask raise
            made["error"] = exc

    thread = threading.Thread(target=connect, daemon=True, name="dask-connect")
    thread.start()
    thread.join(CONNECT_TIMEOUT_S + ANSWER_GRACE_S)
    if "client" in made:
        return made["client"]
    why = (_first_line(made["error"]) if "error" in made else
           f"it took the connection but did not answer as a scheduler within "
           f"{CONNECT_TIMEOUT_S + ANSWER_GRACE_S:g} s")
    raise ConfigError(f"cannot reach the Dask scheduler at {address}: {why}; start one "
                      "(`dask scheduler`, `dask worker ADDRESS`) or drop --scheduler for "
                      "the local pool")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _check_address(address: str) -> None:
    """Refuse a scheduler address Dask cannot parse, before a client is made of it: a
    client made of one raised a clear error, then hung 20 s on leaving and printed a
    traceback."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, location = parse_address(address)
        if scheme not in backends:
            raise ValueError(f"Dask speaks {', '.join(sorted(backends))}, not {scheme!r}")
        if scheme in ("tcp", "tls"):
            _, port = parse_host_port(location)
            if port is not None and not 0 < int(port) < 65536:
                raise ValueError(f"port {port} is not 1-65535")
    except ValueError as exc:
        raise ConfigError(f"--scheduler {address!r} is not a Dask scheduler's address "
                          f"({str(exc).splitlines()[0]}): give tcp://HOST:PORT, as "
                          "`dask scheduler` prints it") from None


def make_executor(workers: int | None, scheduler: str | None) -> Executor:
    """The executor the options ask for: Dask at `scheduler`, else a pool of `workers`
    processes (default: one per core), or this process alone for one worker."""
    if scheduler:
        if workers is not None:
            raise ConfigError("--workers applies to the local pool; a Dask cluster has its "
                              "own workers")
        return DaskCluster(scheduler)
    n = cores() if workers is None else workers
    if n < 1:
        raise ConfigError(f"--workers must be at least 1, got {n}")
    return InProcess() if n == 1 else LocalPool(n)


def add_executor_options(parser, *, default_workers: str = "the number of cores") -> None:
    g = parser.add_argument_group("where episodes run")
    g.add_argument("--workers", type=integer(1, 256), default=None, metavar="N",
                   help=f"local worker processes (default: {default_workers}); results are "
                        "the same for any N, timings are shared between them")
    g.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="run the episodes on an existing Dask distributed cluster instead")
