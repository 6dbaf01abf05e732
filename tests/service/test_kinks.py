"""Kinks of the dilated contour (`objects/kinks.py`): where a tip bridges a hollow narrower
than itself, and what the grasp gate makes of a tip beside one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_if.hand import load_hand
from service.episode.hand_episode import simulate_hand
from service.episode.hand_scenario import HandSettings
from service.localization import chain_kernels
from service.localization.grasp import GraspSpec, hand_quality, joint_torque
from service.localization.objects import kinks
from service.localization.objects.contour import Contour
from service.localization.objects.field import contact_field
from service.localization.objects.presets import preset_object


def knob(lobes: int = 5, depth: float = 0.004, short: float = 0.0015) -> np.ndarray:
    """A knob of `lobes` lobes `depth` deep about a 21 mm radius, one lobe `short` lower:
    valleys far narrower than an 8 mm tip (a held-out check's outline)."""
    t = np.linspace(0, 2 * np.pi, 2800, endpoint=False)
    r = (0.021 + depth * np.cos(lobes * t)
         - short * np.exp(-np.angle(np.exp(1j * t)) ** 2 / 0.05))
    return np.column_stack([r * np.cos(t), r * np.sin(t)])


def write_knob(path: Path) -> Path:
    np.savetxt(path, np.vstack([knob(), knob()[:1]]), delimiter=",", fmt="%.7f")
    return path


def test_a_knob_s_valleys_are_kinks_and_their_sides_differ_by_the_turn():
    found = kinks.kinks(Contour(knob(), name="knob"), 0.008)
    assert len(found.points) == 5  # one per valley
    radii = np.hypot(*found.points.T)
    assert np.all(radii < 0.021 + 0.008)  # in the valleys, not on the lobes
    sides = found.normals[:, [0, 2]]
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", sides[:, 0], sides[:, 1]),
                                        -1, 1)))
    assert np.all(turn > 40)  # a 60-degree corner at an 8 mm tip
    bridge = found.normals[:, 1]
    assert np.allclose(np.linalg.norm(found.normals, axis=-1), 1.0)
    assert np.all(np.einsum("ij,ij->i", bridge, -found.points) < 0)  # points outward
    # a tip smaller than the valleys fits in: no kink
    assert kinks.kinks(Contour(knob(), name="knob"), 0.0005).tree is None


@pytest.mark.parametrize("name", ["ellipse:3", "rounded:3", "keyed:3"])
def test_convex_presets_have_no_kinks(name):
    contour = preset_object(name)
    assert kinks.kinks(contour, 0.008).tree is None


@settings(max_examples=25, deadline=None)
@given(a=st.floats(0.015, 0.04), b=st.floats(0.015, 0.04), r=st.floats(0.002, 0.012))
def test_an_ellipse_has_no_kink_under_any_tip(a, b, r):
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    contour = Contour(np.column_stack([a * np.cos(t), b * np.sin(t)]), name="e")
    assert kinks.kinks(contour, r).tree is None


def test_a_tip_beside_a_kink_is_found_under_a_pose_and_its_normals_turned_with_it():
    contour = Contour(knob(), name="knob")
    found = kinks.kinks(contour, 0.008)
    pose = np.array([0.01, -0.02, 0.7])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    turn = np.array([[c, -s], [s, c]])
    at = pose[:2] + turn @ found.points[0]
    away = pose[:2] + turn @ (found.points[0] + np.array([0.0015, 0.0]))  # 1.5 mm off
    centres = np.array([[at, away]])  # finger 0 at the kink, finger 1 off it
    rows, fingers, normals = kinks.beside(contour, pose[None], centres, np.array([0.008] * 2))
    assert list(rows) == [0] and list(fingers) == [0]
    assert np.allclose(normals[0], found.normals[0] @ turn.T)


def _two_fingers_in_a_valley():
    """Two opposed fingers on the knob, the right tip in a valley (its centre on the kink),
    the left on the opposite lobe; with each finger's joints."""
    hand = load_hand("two-finger")
    contour = Contour(knob(), name="knob")
    field = contact_field(contour)
    found = kinks.kinks(contour, hand.fingers[1].radius)
    valley = found.points[np.argmax(found.points[:, 0])]  # the one at about 0 degrees
    pose = np.array([0.0, 0.0, np.pi - np.arctan2(valley[1], valley[0])])  # valley to -x
    c, s = np.cos(pose[2]), np.sin(pose[2])
    right = np.array([[c, -s], [s, c]]) @ valley
    opposite = np.array([-right[0] + 0.0, right[1]])
    d, _, _ = field.distance(*np.array([[c, s], [-s, c]]) @ opposite)
    left = opposite * (1 + (hand.fingers[0].radius - d) / np.linalg.norm(opposite))
    centres = np.array([[left, right]])
    if right[0] < left[0]:
        centres = centres[:, ::-1]
    joints = []
    for finger, centre in zip(hand.fingers, centres[0], strict=True):
        q, ok = chain_kernels.inverse(finger, np.array([[centre[0], 0.0, centre[1]]]),
                                      np.asarray(finger.home, dtype=np.float64)[None],
                                      iterations=300)
        assert ok[0]
        joints.append(q[0])
    return hand, field, pose, centres, joints


def test_beside_a_kink_the_quality_may_be_the_best_or_least_of_every_way_the_tip_may_rest():
    hand, field, pose, centres, joints = _two_fingers_in_a_valley()
    torque = joint_torque(hand.goal_current_a, hand.fingers[0].joints[0].model)
    args = (field, pose[None], centres, hand.fingers, joints, torque, GraspSpec())
    model, best = hand_quality(*args)[0], hand_quality(*args, beside_kinks=True)[0]
    radii = np.array([f.radius for f in hand.fingers])
    _, beside, normals = kinks.beside(field.contour, pose[None], centres, radii)
    assert len(beside) == 1  # the tip in the valley
    ways = []
    for normal in normals[0]:  # either side, or bridging: each way on its own
        f = int(beside[0])
        contact = centres[0, f] - radii[f] * normal
        ways.append(_quality_with(field, pose, centres, hand, joints, torque, f, normal,
                                  contact))
    assert best == pytest.approx(max(model, *ways))
    assert hand_quality(*args, beside_kinks=True, least=True)[0] == pytest.approx(
        min(model, *ways))  # and at its worst, what the gate's check near the margin fears
    assert max(ways) - min(ways) > 0.5  # a 60-degree corner: the ways differ much
    # away from any kink it is the model's
    shifted = pose + np.array([0.0, 0.0, np.deg2rad(20)])
    far = (field, shifted[None], centres, hand.fingers, joints, torque, GraspSpec())
    assert hand_quality(*far, beside_kinks=True)[0] == hand_quality(*far)[0]


def _quality_with(field, pose, centres, hand, joints, torque, f, normal, contact):
    """The grasp's quality with finger f's contact normal and point replaced."""
    from service.localization import grasp
    from service.localization.objects.rolling import contacts

    radii = np.array([g.radius for g in hand.fingers])
    points, normals = contacts(field, pose[None], centres, radii)
    points[0, f], normals[0, f] = contact, normal
    jac = np.zeros((1, len(hand.fingers), 3, max(len(q) for q in joints)))
    for i, (finger, q) in enumerate(zip(hand.fingers, joints, strict=True)):
        jac[:, i, :, :len(q)] = chain_kernels.jacobians(finger, np.asarray(q)[None])
    forces = grasp._forces(normals, jac, float(torque), GraspSpec().mu)
    return float(grasp.quality(points, pose[None, :2], forces, field.contour.max_radius,
                               GraspSpec().load)[0])


def test_two_fingers_with_a_tip_in_a_knob_s_valley_do_not_drop_it(tmp_path):
    """A held-out check's five-lobed knob, two fingers, seed 28: the right tip started in a
    valley, bridging it (6.01 N in the world); under the model every pose near the truth put
    it on one side (the truth itself -0.36 N), so the gate kept one pose 101 degrees off,
    1 % of the weight, and its first roll dropped the object (0.19 N). Beside a kink the
    gate now takes the most the grasp may hold to judge a pose possible."""
    report = simulate_hand(HandSettings(object=str(write_knob(tmp_path / "knob.csv")),
                                        hand="two-finger", seed=28, noise=True,
                                        max_steps=10))
    assert not report.result.dropped
    assert report.min_quality > GraspSpec().margin_n
