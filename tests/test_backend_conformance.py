"""One conformance suite for every backend: the simulated finger, and the Dynamixel backend
driving emulated servos through the real SDK with the same surface in the loop; and the hand
contract over those, the simulated hand and the Dynamixel hand on the emulated bus.

Plus the end-to-end check: `haptic run --backend dynamixel` on the emulator localizes the
same pose as the simulated finger for the same scenario.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np
import pytest

from firmware_if.backend import (
    Backend,
    FingerMove,
    FingerState,
    HandCommand,
    HandState,
    StepCommand,
)
from firmware_if.dynamixel_backend import DynamixelBackend
from firmware_if.dynamixel_hand import DynamixelHand
from firmware_if.errors import HardwareFault, NotReadyError
from firmware_if.hand import load_hand
from service.episode.runner import execute_step
from service.episode.scenario import RunSettings, draw_truth
from service.episode.simulate import simulate
from service.localization.maps import load_map
from service.localization.objects.presets import preset_object
from service.localization.surface import contact_surface
from sim_backend.clock import ManualClock
from sim_backend.emulator import ServoBus
from sim_backend.emulator.hand_plant import HandPlant
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos
from sim_backend.finger import SimConfig, SimulatedFinger
from sim_backend.hand import HandSimConfig, SimulatedHand

MAP = load_map("peaks")
SURFACE = contact_surface(MAP, 0.008)
HAND = load_hand("spatial")
STEP = 0.01
TOL = 0.001
"""Agreement asked of every backend: 1 mm (encoder quantization of the arm is ~0.3 mm)."""


@dataclass
class Rig:
    backend: Backend
    inject_fault: Callable[[], None]
    start: tuple[float, float, float]


def _sim(start: tuple[float, float, float]) -> Iterator[Rig]:
    finger = SimulatedFinger(MAP, SimConfig(start=start), np.random.default_rng(0))
    yield Rig(finger, lambda: finger.inject_fault("fault drill"), start)
    finger.close()


def _dynamixel(start: tuple[float, float, float]) -> Iterator[Rig]:
    plant = FingerPlant(HAND, MAP, start)
    with ServoBus(hand_bus_servos(HAND, plant), plant=plant) as bus:
        backend = DynamixelBackend(HAND, bus.port)
        yield Rig(backend, lambda: bus.inject_hardware_error(2, 0x20), start)
        backend.close()
        assert not bus.errors, bus.errors  # the emulator handled every packet it was sent


KINDS = {"sim": _sim, "dynamixel": _dynamixel}


@pytest.fixture(params=sorted(KINDS))
def make_rig(request) -> Iterator[Callable[[tuple[float, float, float]], Rig]]:
    made: list[Iterator[Rig]] = []

    def make(start: tuple[float, float, float] = (0.1, 0.1, 0.7)) -> Rig:
        gen = KINDS[request.param](start)
        made.append(gen)
        return next(gen)

    yield make
    for gen in made:
        next(gen, None)


def _active(rig: Rig) -> FingerState:
    rig.backend.open()
    rig.backend.set_torque(True)
    state = rig.backend.read_state()
    assert state.torque_on and not state.moving and state.fault is None
    return state


def _map_xy(rig: Rig, displacement: np.ndarray) -> tuple[float, float]:
    x0, y0, heading = rig.start
    c, s = np.cos(heading), np.sin(heading)
    return (x0 + c * displacement[0] - s * displacement[1],
            y0 + s * displacement[0] + c * displacement[1])


def test_implements_the_contract(make_rig):
    assert isinstance(make_rig().backend, Backend)


def test_nothing_before_open(make_rig):
    with pytest.raises(NotReadyError):
        make_rig().backend.read_state()


def test_stepping_needs_torque(make_rig):
    rig = make_rig()
    rig.backend.open()
    assert not rig.backend.read_state().torque_on
    with pytest.raises(NotReadyError):
        rig.backend.command_step(StepCommand(STEP, 0.0))


def test_steps_move_the_centre_over_the_surface(make_rig):
    rig = make_rig()
    origin = np.asarray(_active(rig).centre)
    z0 = SURFACE.height(*rig.start[:2])
    moves = ((STEP, 0.0), (0.0, STEP), (-STEP, 0.0), (0.0, -2 * STEP))
    for done, (dx, dy) in enumerate(moves, start=1):
        before = np.asarray(rig.backend.read_state().centre) - origin
        state = execute_step(rig.backend, StepCommand(dx, dy))
        assert state.steps_done == done and not state.moving and not state.blocked
        moved = np.asarray(state.centre) - origin
        assert np.allclose(moved[:2] - before[:2], (dx, dy), atol=TOL)
        expected_z = SURFACE.height(*_map_xy(rig, moved)) - z0
        assert abs(moved[2] - expected_z) <= TOL


def test_a_step_off_the_map_is_blocked_and_stays(make_rig):
    rig = make_rig((0.004, 0.1, 0.0))
    origin = np.asarray(_active(rig).centre)
    state = execute_step(rig.backend, StepCommand(-STEP, 0.0))
    assert state.blocked and state.steps_done == 1
    assert np.allclose(state.centre, origin, atol=TOL)
    state = execute_step(rig.backend, StepCommand(STEP, 0.0))
    assert not state.blocked and state.steps_done == 2


def test_a_fault_latches_torque_off_and_clears(make_rig):
    rig = make_rig()
    _active(rig)
    rig.inject_fault()
    state = rig.backend.read_state()
    assert state.fault and not state.torque_on
    with pytest.raises(HardwareFault):
        rig.backend.command_step(StepCommand(STEP, 0.0))
    with pytest.raises(HardwareFault):
        rig.backend.set_torque(True)
    assert isinstance(rig.backend.clear_fault(), list)  # what the reset did, in words
    state = rig.backend.read_state()
    assert state.fault is None and not state.torque_on
    rig.backend.set_torque(True)
    assert not execute_step(rig.backend, StepCommand(STEP, 0.0)).blocked


def test_close_is_idempotent(make_rig):
    rig = make_rig()
    _active(rig)
    rig.backend.close()
    rig.backend.close()
    with pytest.raises(NotReadyError):
        rig.backend.read_state()


def test_same_start_same_readings(make_rig):
    runs = []
    for _ in range(2):
        rig = make_rig()
        origin = np.asarray(_active(rig).centre)
        runs.append([np.asarray(execute_step(rig.backend, StepCommand(dx, dy)).centre) - origin
                     for dx, dy in ((STEP, 0.0), (0.0, STEP))])
        rig.backend.close()
    assert np.array_equal(runs[0], runs[1])


# -- the hand contract, over every implementation (a single finger is a hand of one) ------
@dataclass
class HandRig:
    backend: Backend
    command: HandCommand
    """A step this hand can make from its start."""
    inject_fault: Callable[[], None]


def _hand_of_one(kind: str) -> Callable[[], Iterator[HandRig]]:
    def make() -> Iterator[HandRig]:
        for rig in KINDS[kind]((0.1, 0.1, 0.7)):
            yield HandRig(rig.backend, HandCommand((FingerMove(dx=STEP),)), rig.inject_fault)
    return make


def _sim_hand() -> Iterator[HandRig]:
    hand = SimulatedHand(load_hand("two-finger"), preset_object("blob:2"),
                         HandSimConfig(pose=(0.001, -0.001, 0.7)), np.random.default_rng(0))
    yield HandRig(hand, HandCommand((FingerMove(dz=0.002), None)),
                  lambda: hand.inject_fault("fault drill"))
    hand.close()


def _dynamixel_hand() -> Iterator[HandRig]:
    """The same hand and object as `_sim_hand`, its servos on one emulated bus."""
    sim = SimulatedHand(load_hand("two-finger"), preset_object("blob:2"),
                        HandSimConfig(pose=(0.001, -0.001, 0.7)), np.random.default_rng(0))
    plant = HandPlant(sim)
    with ServoBus(hand_bus_servos(sim.hand, plant), plant=plant) as bus:
        hand = DynamixelHand(sim.hand, bus.port)
        yield HandRig(hand, HandCommand((FingerMove(dz=0.002), None)),
                      lambda: bus.inject_hardware_error(4, 0x20))
        hand.close()
        assert not bus.errors, bus.errors


HAND_KINDS = {"sim": _hand_of_one("sim"), "dynamixel": _hand_of_one("dynamixel"),
              "sim-hand": _sim_hand, "dynamixel-hand": _dynamixel_hand}


@pytest.fixture(params=sorted(HAND_KINDS))
def hand_rig(request) -> Iterator[HandRig]:
    gen = HAND_KINDS[request.param]()
    yield next(gen)
    next(gen, None)


def _execute(backend: Backend, command: HandCommand) -> HandState:
    before = backend.read_hand().fingers[0].steps_done
    backend.command_hand(command)
    for _ in range(20000):
        state = backend.read_hand()
        if not state.moving and state.fingers[0].steps_done > before:
            return state
    raise AssertionError("the hand step never finished")


def test_a_hand_reads_every_finger_and_steps(hand_rig):
    backend = hand_rig.backend
    assert isinstance(backend, Backend)
    with pytest.raises(NotReadyError):
        backend.read_hand()
    backend.open()
    first = backend.read_hand()
    assert len(first.fingers) == len(hand_rig.command.moves)
    names = backend.finger_names()  # one each, told apart (a client shows them)
    assert len(names) == len(first.fingers) == len(set(names))
    assert all(isinstance(n, str) and n for n in names)
    assert not first.dropped and not first.moving
    with pytest.raises(NotReadyError):  # torque off
        backend.command_hand(hand_rig.command)
    backend.set_torque(True)
    state = _execute(backend, hand_rig.command)
    assert all(f.steps_done == 1 and f.torque_on for f in state.fingers)
    moved = [not np.allclose(a.centre, b.centre)
             for a, b in zip(first.fingers, state.fingers, strict=True)]
    assert moved == [m is not None for m in hand_rig.command.moves]  # the others held
    shorthand = backend.read_state()  # a single finger's: the first finger, read again
    assert shorthand.centre == state.fingers[0].centre
    assert shorthand.steps_done == state.fingers[0].steps_done
    with pytest.raises(ValueError, match="at least one finger"):
        backend.command_hand(HandCommand((None,) * len(state.fingers)))


def test_a_hand_fault_latches_and_clears(hand_rig):
    backend = hand_rig.backend
    backend.open()
    backend.set_torque(True)
    hand_rig.inject_fault()
    state = backend.read_hand()
    assert any(f.fault for f in state.fingers) and not any(f.torque_on for f in state.fingers)
    with pytest.raises(HardwareFault):
        backend.command_hand(hand_rig.command)
    backend.clear_fault()
    backend.set_torque(True)
    assert _execute(backend, hand_rig.command).fingers[0].steps_done == 1
    backend.close()
    backend.close()
    with pytest.raises(NotReadyError):
        backend.read_hand()


# -- end to end: the same estimate as the simulated finger -----------------------------------
def _grid_settings(seed: int) -> RunSettings:
    """A pose-table start drawn from the seed; the localizer told to expect sensor noise.

    Noise-free, the localizer demands agreement to 0.5 um, which no encoder gives (a tick of
    this arm is ~0.3 mm at the tip), so hardware runs use the noise-aware sensor model.
    """
    truth = draw_truth(RunSettings(seed=seed), MAP, np.random.default_rng(seed).spawn(4)[0])
    return RunSettings(seed=seed, noise=True, start=truth.as_tuple(), algorithm="elimination",
                       policy="paper")


@pytest.mark.parametrize("seed", [0, 3])
def test_dynamixel_on_the_emulator_localizes_like_the_simulated_finger(seed):
    settings = _grid_settings(seed)
    sim = simulate(settings, MAP)
    buses: list[ServoBus] = []

    def factory(truth):
        plant = FingerPlant(HAND, MAP, truth.as_tuple())
        buses.append(ServoBus(hand_bus_servos(HAND, plant), plant=plant).start())
        return DynamixelBackend(HAND, buses[-1].port)

    try:
        # on hardware a blocked step is no evidence of the map's edge (`for_backend`)
        hil = simulate(replace(settings, walls=False), MAP, backend_factory=factory)
    finally:
        for bus in buses:
            bus.stop()
    assert sim.score.success and hil.score.success
    # with noise the survivor is refined on the readings, which differ by the noise and
    # the encoders' rounding: the same pose, to a millimetre and a degree
    hil_pose, sim_pose = np.asarray(hil.result.estimate.pose), np.asarray(sim.result.estimate.pose)
    np.testing.assert_allclose(hil_pose[:2], sim_pose[:2], atol=1e-3)
    assert abs((hil_pose[2] - sim_pose[2] + np.pi) % (2 * np.pi) - np.pi) < np.deg2rad(1.0)
    assert buses[0].stats["rx_packets"] > 3 * len(hil.result.steps)  # it really used the bus


@pytest.mark.parametrize("noise", [True, False], ids=["noise", "noise-free"])
def test_haptic_run_dynamixel_on_haptic_emulate(tmp_path, capsys, noise):
    """The command-line path: `haptic emulate` then `haptic run --backend dynamixel`.

    Noise-free, the simulator's exact tolerance would eliminate the truth on encoder
    readings; hardware runs assume `HARDWARE_SENSOR_SIGMA` instead.
    """
    from tools import cli
    from tools.emulate_cli import start_emulator

    x, y, heading = _grid_settings(3).start
    start = f"{x!r},{y!r},{float(np.degrees(heading))!r}"
    args = argparse.Namespace(hand="spatial", map="peaks", spacing=None, radius=0.008,
                              step=STEP, algorithm="elimination", policy="paper", noise=noise,
                              max_steps=100, headings=11, sweep=None, seed=3, start=start,
                              no_fast_read=False)
    bus, _ = start_emulator(args)
    try:
        common = ["--seed", "3", "--start", start, "--quiet", "--algorithm", "elimination",
                  "--policy", "paper", *(["--noise"] if noise else [])]
        assert cli.main(["run", "--backend", "dynamixel", "--port", bus.port, "--hand",
                         "spatial", "--json", str(tmp_path / "hil.json"), "--cycle-budget",
                         "50", *common]) == 0
    finally:
        bus.stop()
    assert cli.main(["run", "--json", str(tmp_path / "sim.json"), *common]) == 0
    hil = json.loads((tmp_path / "hil.json").read_text())
    sim = json.loads((tmp_path / "sim.json").read_text())
    assert hil["success"] and sim["success"]
    # the hardware run assumes the encoders' noise, so its survivor is refined on readings
    # that differ from the simulator's: the same pose, to a millimetre and a degree
    assert abs(hil["estimate"]["x"] - sim["estimate"]["x"]) < 1e-3
    assert abs(hil["estimate"]["y"] - sim["estimate"]["y"]) < 1e-3
    turn = hil["estimate"]["heading"] - sim["estimate"]["heading"]
    assert abs((turn + np.pi) % (2 * np.pi) - np.pi) < np.deg2rad(1.0)


def test_torque_off_ends_a_step_under_way_as_blocked(hand_rig):
    """A helper's client saw a simulated finger go on moving for the rest of its step
    after `deactivate` (torque off): `moving` true with torque off, and `steps_done` rising
    later. Servos without torque stop: on every backend the step ends at once, counted and
    blocked, and no step goes on after it."""
    backend = hand_rig.backend
    if isinstance(backend, SimulatedFinger | SimulatedHand):  # a step that lasts: the
        # simulator's clock stands still (its steps are instant by default)
        backend.config = replace(backend.config, step_duration_s=1.0)
        backend._clock = ManualClock()
    backend.open()
    backend.set_torque(True)
    backend.command_hand(hand_rig.command)
    assert backend.read_hand().moving
    backend.set_torque(False)
    cut = backend.read_hand()
    assert not cut.moving
    assert all(f.steps_done == 1 and f.blocked and not f.torque_on for f in cut.fingers)
    later = backend.read_hand()  # (a limp finger on hardware may sag: its centre may move)
    assert not later.moving and all(f.steps_done == 1 for f in later.fingers)
