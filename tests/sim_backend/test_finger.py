"""The simulated finger: hidden pose, contact heights, edges, noise, clock, determinism."""

import numpy as np
import pytest

from firmware_if.backend import StepCommand
from firmware_if.errors import HardwareFault, NotReadyError
from service.errors import ConfigError
from service.localization.maps import peaks
from service.localization.models import NoiseSpec
from service.localization.surface import contact_surface
from sim_backend.clock import ManualClock
from sim_backend.finger import SimConfig, SimulatedFinger

PEAKS = peaks()


def finger(start=(0.1, 0.1, 0.0), noise: NoiseSpec | None = None, seed=0,
           **kw) -> SimulatedFinger:
    f = SimulatedFinger(PEAKS, SimConfig(start=start, noise=noise or NoiseSpec(), **kw),
                        np.random.default_rng(seed))
    f.open()
    f.set_torque(True)
    return f


def test_step_moves_in_the_fingers_own_frame_and_reports_contact_height():
    heading = np.pi / 2
    f = finger(start=(0.1, 0.1, heading), z_offset=0.003)
    f.command_step(StepCommand(0.01, 0.0))
    s = f.read_state()
    assert s.steps_done == 1 and not s.blocked and not s.moving
    assert s.centre[0] == pytest.approx(0.01) and s.centre[1] == pytest.approx(0.0, abs=1e-12)
    # Its +x is the map's +y at heading 90 degrees.
    expected = contact_surface(PEAKS, 0.008).height(0.1, 0.11) - 0.003
    assert s.centre[2] == pytest.approx(expected)


def test_step_off_the_map_is_blocked_and_stays():
    f = finger(start=(0.195, 0.1, 0.0))
    before = f.read_state().centre
    f.command_step(StepCommand(0.01, 0.0))
    s = f.read_state()
    assert s.blocked and s.centre == before and s.steps_done == 1


def test_steps_take_time_on_the_simulators_clock():
    clock = ManualClock()
    f = SimulatedFinger(PEAKS, SimConfig(start=(0.1, 0.1, 0.0), step_duration_s=0.2),
                        np.random.default_rng(0), clock=clock)
    f.open()
    f.set_torque(True)
    f.command_step(StepCommand(0.01, 0.0))
    assert f.read_state().moving
    with pytest.raises(NotReadyError):
        f.command_step(StepCommand(0.01, 0.0))
    clock.advance(0.19)
    assert f.read_state().moving
    clock.advance(0.02)
    s = f.read_state()
    assert not s.moving and s.steps_done == 1 and s.centre[0] == pytest.approx(0.01)


def test_noise_is_seeded_bit_for_bit():
    def trace(seed):
        f = finger(noise=NoiseSpec.realistic(), seed=seed)
        out = []
        for _ in range(5):
            f.command_step(StepCommand(0.0, 0.01))
            out.append(f.read_state().centre)
        return out

    assert trace(4) == trace(4)
    assert trace(4) != trace(5)


def test_noise_has_the_configured_size():
    f = finger(noise=NoiseSpec(step_length_fraction=0.02, measurement_sigma=1e-4), seed=1)
    xs = []
    for _ in range(40):
        before = f.read_state().centre[0]
        f.command_step(StepCommand(0.001, 0.0))
        xs.append(f.read_state().centre[0] - before)
        f.command_step(StepCommand(-0.001, 0.0))
    assert 0.0008 < np.mean(xs) < 0.0012 and np.std(xs) > 5e-5


def test_lifecycle_guards():
    f = SimulatedFinger(PEAKS, SimConfig(start=(0.1, 0.1, 0.0)), np.random.default_rng(0))
    with pytest.raises(NotReadyError, match="open"):
        f.read_state()
    f.open()
    with pytest.raises(NotReadyError, match="torque"):
        f.command_step(StepCommand(0.01, 0.0))
    f.set_torque(True)
    f.inject_fault("overload")
    assert f.read_state().fault == "overload" and not f.read_state().torque_on
    with pytest.raises(HardwareFault):
        f.set_torque(True)
    f.clear_fault()
    f.set_torque(True)
    f.command_step(StepCommand(0.01, 0.0))
    f.close()


def test_start_off_the_map_is_rejected():
    f = SimulatedFinger(PEAKS, SimConfig(start=(0.5, 0.1, 0.0)), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="outside the map"):
        f.open()
