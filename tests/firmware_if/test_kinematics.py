"""Kinematics: Jacobian against finite differences, IK round trips, limits and reach."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_if import kinematics as kin
from firmware_if.hand import load_hand

HANDS = {name: load_hand(name) for name in ("planar", "spatial")}


def joint_vectors(name: str):
    hand = HANDS[name]
    return st.tuples(*(st.floats(j.limits[0], j.limits[1]) for j in hand.joints)).map(np.array)


@pytest.mark.parametrize("name", sorted(HANDS))
@given(data=st.data())
def test_jacobian_matches_finite_differences(name, data):
    hand = HANDS[name]
    q = data.draw(joint_vectors(name))
    eps = 1e-6
    numeric = np.stack([(kin.forward(hand, q + eps * e) - kin.forward(hand, q - eps * e))
                        / (2 * eps) for e in np.eye(len(q))], axis=1)
    assert np.allclose(kin.jacobian(hand, q), numeric, atol=1e-8)


@pytest.mark.parametrize("name", sorted(HANDS))
@given(data=st.data())
def test_ik_round_trip_from_home(name, data):
    hand = HANDS[name]
    q_true = data.draw(joint_vectors(name))
    target = kin.forward(hand, q_true)
    result = kin.inverse(hand, target, np.array(hand.home), tolerance=1e-6, iterations=200)
    if result.reachable:
        assert np.linalg.norm(kin.forward(hand, result.q) - target) <= 1e-6
    assert np.all(result.q >= hand.lower) and np.all(result.q <= hand.upper)


def test_small_moves_are_reached():
    hand = HANDS["spatial"]
    home = np.array(hand.home)
    centre = kin.forward(hand, home)
    for delta in ([0.01, 0, 0], [0, 0.01, 0], [-0.01, 0, -0.005], [0, -0.01, 0.01]):
        result = kin.inverse(hand, centre + delta, home)
        assert result.reachable
        assert np.allclose(kin.forward(hand, result.q), centre + delta, atol=1e-5)


def test_unreachable_targets_are_reported_not_raised():
    hand = HANDS["spatial"]
    home = np.array(hand.home)
    far = kin.inverse(hand, [1.0, 0.0, 0.0], home)
    assert not far.reachable and far.error > 0.5
    planar = HANDS["planar"]
    off_plane = kin.inverse(planar, kin.forward(planar, planar.home) + [0, 0.01, 0],
                            np.array(planar.home))
    assert not off_plane.reachable and abs(off_plane.error - 0.01) < 1e-4


def test_batches_equal_rows():
    hand = HANDS["spatial"]
    rng = np.random.default_rng(0)
    q = rng.uniform(hand.lower, hand.upper, size=(50, 3))
    batch = kin.forward(hand, q)
    assert np.allclose(batch, [kin.forward(hand, row) for row in q])
    assert np.allclose(kin.jacobian(hand, q), [kin.jacobian(hand, row) for row in q])
    targets = batch + 0.002
    result = kin.inverse(hand, targets, q)
    assert result.q.shape == (50, 3) and result.reachable.shape == (50,)


@pytest.mark.parametrize("finger", load_hand("three-finger").fingers, ids=lambda f: f.name)
def test_a_finger_of_a_hand_starts_at_its_base(finger):
    rng = np.random.default_rng(0)
    q = rng.uniform(finger.lower, finger.upper)
    rot, origin = kin.base_frame(finger)
    alone = dataclasses.replace(finger, base=(0.0, 0.0, 0.0))
    assert np.allclose(kin.forward(finger, q), rot @ kin.forward(alone, q) + origin)
    assert kin.forward(finger, q)[1] == pytest.approx(0.0)  # in the hand's x-z plane
    eps = 1e-6
    numeric = np.stack([(kin.forward(finger, q + eps * e) - kin.forward(finger, q - eps * e))
                        / (2 * eps) for e in np.eye(len(q))], axis=1)
    assert np.allclose(kin.jacobian(finger, q), numeric, atol=1e-8)
    target = kin.forward(finger, q)
    assert kin.inverse(finger, target, np.array(finger.home), iterations=300).reachable


def test_a_target_out_of_reach_stops_the_solver_once_it_stalls(monkeypatch):
    """A planar finger asked to step out of its plane ran all 100 iterations at the nearest
    posture: 10 ms in one tick of hapticd's 5 ms loop, every blocked step. It stops once an
    iteration brings the centre no nearer, at the same posture to a micrometre."""
    planar = HANDS["planar"]
    home = np.array(planar.home)
    target = kin.forward(planar, home) + [0.003, 0.01, 0]
    calls = {"n": 0}
    solve = kin._centre_and_jacobian

    def counted(hand, q):
        calls["n"] += 1
        return solve(hand, q)

    monkeypatch.setattr(kin, "_centre_and_jacobian", counted)
    stalled = kin.inverse(planar, target, home)
    assert calls["n"] < 30 and not stalled.reachable
    monkeypatch.setattr(kin, "STALLED", -np.inf)  # never stalls: all 100 iterations
    full = kin.inverse(planar, target, home)
    np.testing.assert_allclose(kin.forward(planar, stalled.q), kin.forward(planar, full.q),
                               atol=1e-6)
