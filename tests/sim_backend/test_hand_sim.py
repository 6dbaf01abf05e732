"""The simulated hand: fingers close on the object, roll along it, drop it when the grasp
gives, refuse what they cannot reach, and turn it when they manipulate."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_if.backend import FingerMove, HandCommand
from firmware_if.errors import NotReadyError
from firmware_if.hand import load_hand
from service.localization.models import NoiseSpec
from service.localization.objects import kernels, rolling
from service.localization.objects.field import contact_field
from service.localization.objects.presets import preset_object
from sim_backend.clock import ManualClock
from sim_backend.hand import HandSimConfig, SimulatedHand

TWO = load_hand("two-finger")
BLOB = preset_object("blob:2")
POSE = (0.001, -0.001, 0.7)


NO_NOISE = NoiseSpec()


def opened(pose=POSE, noise=NO_NOISE, seed=0, **kw) -> SimulatedHand:
    sim = SimulatedHand(TWO, BLOB, HandSimConfig(pose=pose, noise=noise, **kw),
                        np.random.default_rng(seed))
    sim.open()
    sim.set_torque(True)
    return sim


def centres(sim: SimulatedHand) -> np.ndarray:
    return np.array([[f.centre[0], f.centre[2]] for f in sim.read_hand().fingers])


def gaps(pose, points) -> np.ndarray:
    """How far each fingertip centre is from touching the object (metres)."""
    field = contact_field(BLOB)
    return kernels.residuals(*field.args, np.asarray(pose, dtype=float)[None],
                             np.ascontiguousarray(points), np.full(len(points), 0.008))[0]


def test_fingers_close_on_the_object_and_hold_it():
    sim = opened()
    c = centres(sim)
    np.testing.assert_allclose(gaps(sim.pose, c), 0.0, atol=2e-6)
    assert c[0, 0] < 0 < c[1, 0]  # left and right of the object
    assert sim.quality > sim.config.grasp.threshold_n


def test_an_exploring_step_rolls_one_finger_along_the_object():
    sim = opened()
    before = centres(sim)
    sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))
    after = centres(sim)
    assert after[0, 1] - before[0, 1] == pytest.approx(0.003, abs=5e-4)
    np.testing.assert_array_equal(after[1], before[1])  # the other finger held
    np.testing.assert_allclose(gaps(sim.pose, after), 0.0, atol=2e-6)  # still touching
    assert sim.pose == POSE  # the object stayed put
    assert sim.read_hand().fingers[0].steps_done == 1


def test_out_of_reach_is_blocked_and_nothing_moves():
    sim = opened()
    before = centres(sim)
    sim.command_hand(HandCommand((FingerMove(dz=0.2), None)))
    state = sim.read_hand()
    assert state.fingers[0].blocked and not state.dropped
    np.testing.assert_array_equal(centres(sim), before)


def test_rolling_too_far_drops_the_object():
    sim = opened()
    for _ in range(30):
        sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))
        if sim.read_hand().dropped:
            break
    assert sim.read_hand().dropped
    assert sim.min_quality < sim.config.grasp.margin_n
    with pytest.raises(NotReadyError, match="dropped"):
        sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))


def test_a_clamped_object_is_never_dropped_nor_manipulated():
    sim = opened(fixed=True)
    for _ in range(10):
        sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))
    assert not sim.read_hand().dropped
    with pytest.raises(NotReadyError, match="clamped"):
        sim.command_hand(HandCommand((FingerMove(roll=0.1), FingerMove(roll=0.1))))


def test_manipulation_turns_the_object_as_planned():
    sim = opened()
    field = contact_field(BLOB)
    moves, rolls = rolling.plan_turn(field, np.array(POSE), centres(sim),
                                     np.array([0.008, 0.008]), 0.3)
    sim.command_hand(HandCommand(tuple(FingerMove(dx=m[0], dz=m[1], roll=r)
                                       for m, r in zip(moves, rolls, strict=True))))
    assert not sim.read_hand().dropped
    assert sim.pose[2] - POSE[2] == pytest.approx(0.3, abs=0.01)
    assert np.hypot(sim.pose[0] - POSE[0], sim.pose[1] - POSE[1]) < 5e-4  # turned in place
    np.testing.assert_allclose(gaps(sim.pose, centres(sim)), 0.0, atol=2e-6)


def test_twist_recovers_a_consistent_motion():
    rng = np.random.default_rng(3)
    points = rng.normal(0, 0.02, (1, 3, 2))
    normals = rng.normal(size=(1, 3, 2))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    radii = np.array([0.008, 0.01, 0.006])
    truth = np.array([0.001, -0.0005, 0.05])
    lever = points[0] - 0.0
    velocity = truth[:2] + truth[2] * np.column_stack([-lever[:, 1], lever[:, 0]])
    rolls = rng.normal(0, 0.1, 3)
    t = np.column_stack([-normals[0, :, 1], normals[0, :, 0]])
    moves = velocity + (radii * rolls)[:, None] * t  # tips roll, centres follow: no slip
    np.testing.assert_allclose(kernels.twist(points[0], normals[0], np.zeros(2), radii, moves,
                                             rolls), truth, atol=1e-10)


def test_same_seed_same_readings_and_noise_at_b2_level():
    noise = NoiseSpec.realistic(0.01)
    a, b = opened(noise=noise, seed=4), opened(noise=noise, seed=4)
    for sim in (a, b):
        sim.command_hand(HandCommand((None, FingerMove(dz=-0.002))))
    np.testing.assert_array_equal(centres(a), centres(b))
    errors = gaps(a.pose, centres(a))
    assert 1e-6 < np.max(np.abs(errors)) < 1e-3


@pytest.mark.parametrize("command", [
    HandCommand((FingerMove(dz=0.003), None)),
    HandCommand((FingerMove(dz=0.001, roll=0.05), FingerMove(dz=0.001, roll=-0.05))),
], ids=["explore", "manipulate"])
def test_a_timed_step_works_out_a_substep_per_read_and_ends_where_an_instant_one_does(
        command):
    """hapticd reads the hand once a tick: a step's physics is spread over the reads (no
    tick carries a whole step), and draws the same noise, so it ends bitwise where a step
    worked out at once ends."""
    noise = NoiseSpec(measurement_sigma=2e-4, step_length_fraction=0.05,
                      step_direction_sigma=0.05)
    clock = ManualClock()
    timed = SimulatedHand(TWO, BLOB, HandSimConfig(pose=POSE, noise=noise,
                                                   step_duration_s=0.05),
                          np.random.default_rng(3), clock)
    timed.open()
    timed.set_torque(True)
    instant = opened(noise=noise, seed=3)
    instant.command_hand(command)
    timed.command_hand(command)
    start = (timed.pose, timed.centres)
    substeps = timed.config.substeps
    for _ in range(substeps - 1):  # the motion is under way, not yet over
        timed.read_hand()
        assert (timed.pose, timed.centres.tolist()) == (start[0], start[1].tolist())
    timed.read_hand()  # the last substep: the object and fingers are where they went
    assert timed.pose == instant.pose
    np.testing.assert_array_equal(timed.centres, instant.centres)
    assert timed.read_hand().fingers[0].moving and timed.steps_done == 0  # not due yet
    clock.advance(0.05)
    state = timed.read_hand()
    assert not state.fingers[0].moving and timed.steps_done == instant.steps_done == 1
    np.testing.assert_array_equal(centres(timed), centres(instant))


def test_a_step_due_before_its_substeps_were_read_is_finished_at_once():
    """A late tick (reads slower than the substeps) finishes what is left in one read."""
    clock = ManualClock()
    timed = SimulatedHand(TWO, BLOB, HandSimConfig(pose=POSE, step_duration_s=0.05),
                          np.random.default_rng(0), clock)
    timed.open()
    timed.set_torque(True)
    instant = opened()
    for sim in (timed, instant):
        sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))
    timed.read_hand()
    clock.advance(0.06)
    assert not timed.read_hand().fingers[0].moving
    np.testing.assert_array_equal(centres(timed), centres(instant))


def test_a_step_under_way_when_the_hand_closes_is_gone_when_it_opens_again():
    """Closing mid-step (hapticd's reset, a reconfigure) ends the step: the hand opens
    again holding the object as a fresh one does, with nothing of the old step left to
    move it."""
    clock = ManualClock()
    sim = SimulatedHand(TWO, BLOB, HandSimConfig(pose=POSE, step_duration_s=0.05),
                        np.random.default_rng(0), clock)
    sim.open()
    sim.set_torque(True)
    sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))
    sim.read_hand()  # one substep done, the rest under way
    sim.close()
    sim.open()
    sim.set_torque(True)
    fresh = opened()
    for _ in range(sim.config.substeps + 1):
        state = sim.read_hand()
    clock.advance(0.1)
    state = sim.read_hand()
    assert not state.fingers[0].moving and sim.steps_done == 0
    np.testing.assert_array_equal(sim.centres, fresh.centres)
    sim.command_hand(HandCommand((FingerMove(dz=0.003), None)))  # not refused as busy


def test_the_worlds_slope_off_the_model_has_the_sd_the_noise_spec_states():
    """The gate allows the world's normals to turn by `NoiseSpec.surface_slope_sd` (times
    `grasp_gated.TILT`). On an outline long beside the correlation length, the simulated
    world's slope off the model has that sd; on a preset's (a dozen correlation lengths)
    the draw's scaling to sd sigma exactly makes it larger (1.0-1.8 times on ellipse:3,
    12 seeds)."""
    from service.localization.objects.contour import Contour
    from sim_backend.hand import perturbed_contour

    noise = NoiseSpec.realistic(unit=0.01)

    def slope_sds(model, seeds):
        points, _ = model.resampled(0.0005)
        out = []
        for seed in seeds:
            world = perturbed_contour(model, noise.surface_sigma, noise.surface_correlation,
                                      np.random.default_rng(seed))
            turn = _heading(world.points) - _heading(points)
            out.append(np.std(np.angle(np.exp(1j * turn))))
        return np.array(out)

    a = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    long = Contour(points=0.2 * np.column_stack([np.cos(a), np.sin(a)]), name="long")
    assert np.mean(slope_sds(long, range(4))) == pytest.approx(noise.surface_slope_sd,
                                                                rel=0.05)
    short = slope_sds(preset_object("ellipse:3"), range(12)) / noise.surface_slope_sd
    assert short.min() > 0.9 and short.max() < 2.0


def _heading(points: np.ndarray) -> np.ndarray:
    step = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    return np.arctan2(step[:, 1], step[:, 0])
