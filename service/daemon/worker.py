"""The daemon's compute process: maps, localizer and policy, away from the control loop.

`hapticd`'s loop thread does bus I/O, kinematics, the lease watchdog and the stream; every
piece of slow work (loading and checking a map, building a contact surface, constructing a
localizer, an update with its global checks, a policy's choice) runs here, in a process of
its own (a fresh interpreter, `python -m service.daemon.worker`) at a lower priority, so
the loop keeps its rate whatever the localizer costs, and a localizer that crashes takes
only this process down.

The two talk over a socket pair in the wire format (`service.wire.envelope`: msgpack maps, arrays
as typed bytes, never pickle). Each request carries `req`; each reply echoes it, so the
loop drops answers to requests it has moved past. Requests:

    setup    {req, settings, backend, cloud_points}   -> ready {truth, world} | error
    commit   {req}                  the prepared setup becomes the current one
    discard  {req}                  it is dropped
    start    {req, truth}           -> belief {estimate, cloud, move, ...}
    update   {req, measurement, blocked_here, displacement, decide} -> belief
    cancel   {req}                  the episode under way is dropped
    exit     {}

An update runs in slices (the localizers' anytime `work`); between slices the process
looks at the pipe, so a `cancel` (or a new request) cuts a long update short.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from service.errors import InputError, MapError
from service.wire import envelope as wire

log = logging.getLogger("hapticd.worker")
SLICE_S = 0.02
"""Longest localizer slice between looks at the pipe."""
NICE = 5
"""The compute process yields the CPU to the control loop when both want it."""


@dataclass
class Scenario:
    """One configured scenario: settings, the localizer's surface, the seeded streams."""

    settings: Any
    surface: Any
    loc_rng: np.random.Generator
    policy_rng: np.random.Generator
    first: bool = True
    """The next episode is the first after configure: it uses `haptic run`'s streams."""


class Worker:
    """The compute process's state and request handlers (also usable in-process, for tests)."""

    def __init__(self, send: Any) -> None:
        self._send = send
        self.current: Scenario | None = None
        self.candidate: Scenario | None = None
        self.cloud_points = 500
        self.localizer: Any = None
        self.policy: Any = None
        self.policy_rng: np.random.Generator | None = None
        self.truth: tuple[float, float, float] | None = None
        self._files: list[Path] = []

    # -- configuration -----------------------------------------------------------------
    def setup(self, req: int, body: dict[str, Any]) -> None:
        from service.episode.scenario import (
            RunSettings,
            draw_truth,
            episode_streams,
            for_backend,
            prepare_localizers,
            surface_for,
        )

        self._drop_files()  # a previous setup's, never mapped
        fields = dict(body["settings"])
        if fields.get("start") is not None:
            fields["start"] = tuple(fields["start"])
        settings = for_backend(RunSettings(**fields), body["backend"])
        self.cloud_points = int(body.get("cloud_points", 500))
        try:
            surface = surface_for(settings)
        except MapError as exc:
            raise _quiet_map_error(settings.map, exc) from None
        truth_rng, world_rng, loc_rng, policy_rng = episode_streams(settings.seed)
        prepare_localizers()
        candidate = Scenario(settings, surface, loc_rng, policy_rng)
        self._build(candidate, candidate.loc_rng)  # options and map checked now, not later
        truth, world = None, None
        if body["backend"] == "sim":
            truth = draw_truth(settings, surface.map, truth_rng).as_tuple()
            world = self._world(settings, surface, world_rng)
        self.candidate = candidate
        self._send("ready", req, {"truth": None if truth is None else list(truth),
                                  "world": world})

    def _world(self, settings: Any, surface: Any, rng: np.random.Generator) -> dict[str, Any]:
        """The simulated world (the map as the finger really meets it, perturbed by B2's
        noise), built here and handed over as two memory-mapped arrays, with the state of
        the world's random stream after the perturbation, so the loop's simulated finger
        behaves as `haptic run`'s does."""
        from service.localization.surface import contact_surface
        from sim_backend.world import perturbed

        noise = settings.noise_spec
        world = perturbed(surface.map, noise.surface_sigma, noise.surface_correlation, rng)
        centre = contact_surface(world, settings.radius).centre_heights
        folder = Path(os.environ.get("HAPTIC_SHM", "/dev/shm"))
        if not folder.is_dir():
            folder = Path(tempfile.gettempdir())
        paths = {}
        for name, array in (("heights", world.heights), ("centre", centre)):
            fd, path = tempfile.mkstemp(prefix=f"hapticd-{name}-", suffix=".npy", dir=folder)
            with os.fdopen(fd, "wb") as f:
                np.save(f, np.asarray(array), allow_pickle=False)
            paths[name] = path
            self._files.append(Path(path))
        return {"paths": paths, "spacing": world.spacing, "name": world.name,
                "rng": json.dumps(rng.bit_generator.state)}

    def _drop_files(self) -> None:
        for path in self._files:
            path.unlink(missing_ok=True)  # the loop has mapped them, or never will
        self._files.clear()

    def commit(self, req: int, body: dict[str, Any]) -> None:
        if self.candidate is not None:
            self.current, self.candidate = self.candidate, None
            self.localizer = None
        self._drop_files()

    def discard(self, req: int, body: dict[str, Any]) -> None:
        self.candidate = None
        self._drop_files()

    # -- episodes ------------------------------------------------------------------------
    def _build(self, scenario: Scenario, loc_rng: np.random.Generator) -> Any:
        from service.episode.scenario import build_localizer, build_policy

        localizer = build_localizer(scenario.settings, scenario.surface, loc_rng)
        self.policy = build_policy(scenario.settings)
        return localizer

    def start(self, req: int, body: dict[str, Any]) -> None:
        from service.localization.localizers.base import Measurement

        sc = self._scenario()
        if sc.first:  # as `haptic run` seeds it; later episodes spawn fresh streams
            loc_rng, self.policy_rng = sc.loc_rng, sc.policy_rng
            sc.loc_rng = sc.loc_rng.spawn(1)[0]
            sc.first = False
        else:
            loc_rng, self.policy_rng = sc.loc_rng.spawn(2)
        self.localizer = self._build(sc, loc_rng)
        self.truth = None if body.get("truth") is None else tuple(body["truth"])
        t0 = time.monotonic_ns()
        self.localizer.start(Measurement(step=0, displacement=np.zeros(3),
                                         t_ns=int(body.get("t_ns", 0))))
        self._belief(req, body, t0)

    def update(self, req: int, body: dict[str, Any], interrupted: Any) -> None:
        from service.localization.localizers.base import Budget, Measurement

        if self.localizer is None:
            raise InputError("no episode under way")
        m = body["measurement"]
        measurement = Measurement(step=int(m["step"]), blocked=bool(m["blocked"]),
                                  displacement=np.asarray(m["displacement"], dtype=float),
                                  t_ns=int(m["t_ns"]), command=tuple(m["command"]))
        t0 = time.monotonic_ns()
        self.localizer.begin_update(measurement)
        while not self.localizer.work(Budget.seconds(SLICE_S)):
            if interrupted():
                self.localizer = None  # cut short: the next request decides what follows
                return
        self._belief(req, body, t0)

    def cancel(self, req: int, body: dict[str, Any]) -> None:
        self.localizer = None

    def _belief(self, req: int, body: dict[str, Any], t0: int) -> None:
        """Reply with the estimate, a cloud of the same moment and, if asked and the
        episode goes on, the policy's next move."""
        from service.localization.policies.base import PolicyInput

        sc = self._scenario()
        est = self.localizer.estimate()
        update_ms = (time.monotonic_ns() - t0) / 1e6
        hyp = self.localizer.hypotheses(limit=self.cloud_points)
        move, policy_ms = None, 0.0
        going_on = not (est.converged or est.candidates == 0)
        if body.get("decide", True) and going_on:
            t1 = time.perf_counter()
            view = PolicyInput(hypotheses=self.localizer.hypotheses(),
                               displacement=np.asarray(body.get("displacement", (0, 0)),
                                                       dtype=float)[:2],
                               blocked=frozenset(int(b) for b in body.get("blocked_here", [])),
                               surface=sc.surface, step_length=sc.settings.step,
                               rng=self.policy_rng, walls=sc.settings.walls, estimate=est)
            move = int(self.policy.next_move(view))
            policy_ms = (time.perf_counter() - t1) * 1e3
        self._send("belief", req, {
            "estimate": estimate_fields(est), "update_ms": update_ms, "policy_ms": policy_ms,
            "move": move, "poses": hyp.poses.astype(np.float32),
            "weights": hyp.weights.astype(np.float32),
            "true_pose_eliminated": self._truth_eliminated(sc)})

    def _truth_eliminated(self, sc: Scenario) -> bool | None:
        """Whether a discrete localizer dropped the simulator's true pose (None elsewhere)."""
        retains = getattr(self.localizer, "retains", None)
        if retains is None or self.truth is None:
            return None
        kept = retains(self.truth, 1e-6 * sc.settings.step, 1e-6)
        return None if kept is None else not kept

    def _scenario(self) -> Scenario:
        if self.current is None:
            raise InputError("the compute process has no scenario: configure first")
        return self.current


def estimate_fields(est: Any) -> dict[str, Any]:
    """An Estimate as plain numbers (None for nothing or not finite)."""

    def num(v: float | None) -> float | None:
        return float(v) if v is not None and np.isfinite(v) else None

    def pose(p: Any) -> list[float] | None:
        return None if p is None else [float(v) for v in p]

    return {"pose": pose(est.pose), "candidates": int(est.candidates),
            "converged": bool(est.converged), "position_sd": num(est.position_sd),
            "heading_sd": num(est.heading_sd), "mode_mass": num(est.mode_mass),
            "runner_up": pose(est.runner_up),
            "runner_up_mass": None if est.runner_up is None else num(est.runner_up_mass)}


def _quiet_map_error(spec: str, exc: MapError) -> MapError:
    """A map *file* error names the path only: what the file holds, and whether it exists,
    is not the business of a remote client (the detail goes to the daemon's log)."""
    if Path(spec).suffix.lower() not in (".npy", ".csv", ".txt") and "/" not in spec:
        return exc  # a preset: its error says nothing about files
    log.warning("map %s: %s", spec, exc)
    return MapError(f"map file '{spec}' cannot be used: it is missing, unreadable or not a "
                    f"grid of heights in metres (the daemon's log says which)")


HANDLERS = ("setup", "commit", "discard", "start", "cancel")


def serve(conn: Connection) -> None:
    """The compute process's main loop (the target of the spawned process)."""
    from threadpoolctl import threadpool_limits

    with contextlib.suppress(OSError):  # (a lower priority is a courtesy, not a must)
        os.nice(NICE)
    threadpool_limits(limits=1)
    seq = [0]

    def send(kind: str, req: int, fields: dict[str, Any]) -> None:
        seq[0] += 1
        try:
            conn.send_bytes(wire.encode(kind, seq[0], {"req": req, **fields}))
        except OSError:  # (BrokenPipeError) the daemon closed its end: it is stopping
            raise _DaemonGone from None

    worker = Worker(send)
    backlog: list[wire.Message] = []

    def interrupted() -> bool:
        """A request arrived: the update under way gives way to it."""
        while conn.poll(0):
            backlog.append(_receive(conn))
        return bool(backlog)

    while True:
        msg = backlog.pop(0) if backlog else _receive(conn)
        if msg is None or msg.type == "exit":
            break
        try:
            _handle(worker, msg, send, interrupted)
        except _DaemonGone:
            break
    worker._drop_files()


class _DaemonGone(Exception):
    """The daemon's end of the socket is closed: nobody is left to answer."""


def _handle(worker: Worker, msg: wire.Message, send: Any, interrupted: Any) -> None:
    """One request; its refusal or failure is a reply (bad_config, internal)."""
    req = int(msg.get("req", 0))
    try:
        if msg.type == "update":
            worker.update(req, msg.body, interrupted)
        elif msg.type in HANDLERS:
            getattr(worker, msg.type)(req, msg.body)
    except _DaemonGone:
        raise
    except InputError as exc:
        send("error", req, {"code": "bad_config", "message": str(exc)})
    except Exception as exc:  # a localizer or policy bug: reported, the process lives on
        log.error("compute process: %s", traceback.format_exc())
        send("error", req, {"code": "internal", "message": f"{type(exc).__name__}: {exc}"})


def _receive(conn: Connection) -> wire.Message | None:
    try:
        return wire.decode(conn.recv_bytes())
    except (EOFError, OSError):
        return None  # the daemon is gone


def main(argv: list[str]) -> int:
    """`python -m service.daemon.worker FD`: serve the daemon on the inherited socket FD."""
    import sys

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter('{"event": "worker", "message": %(message)r}'))
    log.addHandler(handler)
    log.propagate = False
    serve(Connection(int(argv[0])))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
