"""The grasp model: Eq. 8's grasp map, Ferrari-Canny epsilon, and the holding quality."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from firmware_if import kinematics as kin
from firmware_if.hand import load_hand
from service.errors import ConfigError
from service.localization import grasp as g
from service.localization.objects.field import contact_field
from service.localization.objects.presets import preset_object
from service.localization.objects.rolling import contacts


def on_disc(angles_deg, radius=0.025):
    a = np.deg2rad(np.asarray(angles_deg, dtype=float))
    normals = np.column_stack([np.cos(a), np.sin(a)])
    return normals * radius, normals


def test_grasp_map_sums_the_contact_wrenches():
    points, normals = on_disc([180, 10, 280])
    rng = np.random.default_rng(0)
    f = rng.normal(size=6)  # (push, tangential) per contact
    G = g.grasp_map(points, normals, np.array([0.001, -0.002]), 0.03)
    forces = -normals * f[0::2, None] + g.tangents(normals) * f[1::2, None]
    direct = g.wrenches(points, forces, np.array([0.001, -0.002]), 0.03).sum(axis=0)
    np.testing.assert_allclose(G @ f, direct, atol=1e-12)


def test_epsilon_follows_the_friction_cones():
    opposed = g.epsilon(*on_disc([180, 0]), np.zeros(2), 0.025, 0.5)
    tilted = g.epsilon(*on_disc([180, 40]), np.zeros(2), 0.025, 0.5)
    beyond = g.epsilon(*on_disc([180, 60]), np.zeros(2), 0.025, 0.5)  # outside the cones
    assert opposed > tilted > 0 and beyond == 0.0
    assert g.epsilon(*on_disc([180, 60]), np.zeros(2), 0.025, 0.8) > 0  # more friction
    assert g.epsilon(*on_disc([90, 210, 330]), np.zeros(2), 0.025, 0.5) > 0


def test_quality_is_the_distance_to_the_minkowski_sum():
    rng = np.random.default_rng(1)
    for _ in range(60):
        n = int(rng.integers(2, 4))
        points, normals = on_disc(rng.uniform(0, 360, n), rng.uniform(0.02, 0.03, (n, 1)))
        forces = g.force_vertices(normals, 0.5, rng.uniform(0.5, 4, (n, 3)))
        load = rng.normal([0, 0.5, 0], [0.5, 0.5, 0.3])
        q = float(g.quality(points, np.zeros(2), forces, 0.03, load))
        corners = g.wrenches(points[:, None, :], forces, np.zeros(2), 0.03)
        sums = np.array([sum(c) for c in itertools.product(
            *[np.vstack([np.zeros(3), corners[i]]) for i in range(n)])])
        hull = ConvexHull(sums)
        reference = float(np.min(-(hull.equations[:, :3] @ load + hull.equations[:, 3])))
        if reference > 0:  # inside: the exact distance to the nearest facet
            assert q == pytest.approx(reference, abs=1e-9)
        else:  # outside: the grasp cannot carry the load
            assert q <= 1e-12


def test_weight_and_force_bounds_lower_the_quality():
    points, normals = on_disc([180, 0])
    strong = g.force_vertices(normals, 0.5, np.full((2, 3), 3.0))
    weak = g.force_vertices(normals, 0.5, np.full((2, 3), 0.3))
    free = float(g.quality(points, np.zeros(2), strong, 0.025, np.zeros(3)))
    loaded = float(g.quality(points, np.zeros(2), strong, 0.025, np.array([0, 0.5, 0])))
    assert free > loaded > 0
    assert float(g.quality(points, np.zeros(2), weak, 0.025, np.array([0, 0.5, 0]))) < 0
    batch = g.quality(np.stack([points] * 4), np.zeros((4, 2)), np.stack([strong] * 4), 0.025,
                      np.zeros(3))
    np.testing.assert_allclose(batch, free)


def test_tip_force_limits_saturate_a_joint():
    finger = load_hand("two-finger").fingers[0]
    q = np.array(finger.home)
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.0, -0.8]])
    limits = kin.max_tip_force(finger, q, 0.2, directions)
    torques = np.abs((directions * limits[:, None]) @ kin.jacobian(finger, q))
    np.testing.assert_allclose(torques.max(axis=1), 0.2)
    assert g.joint_torque(0.15, "XM430-W350") == pytest.approx(0.15 * 4.1 / 2.3)


@pytest.mark.parametrize("name", ["two-finger", "three-finger"])
def test_hand_quality_pushes_each_finger_to_its_joint_limits(name):
    """The compiled hand quality is the numpy composition: contacts, the cone edges and
    straight in at each finger's `max_tip_force`, the Minkowski-sum distance."""
    hand = load_hand(name)
    field = contact_field(preset_object("blob:3"))
    rng = np.random.default_rng(4)
    batch, n = 30, len(hand.fingers)
    poses = np.column_stack([rng.normal(0, 0.002, (batch, 2)), rng.uniform(-np.pi, np.pi,
                                                                            batch)])
    angles = [rng.uniform(f.lower, f.upper, (batch, len(f.lower))) for f in hand.fingers]
    angles[0] = np.array(hand.fingers[0].home)  # one finger's angles shared by every row
    centres = np.stack([kin.forward(f, q)[..., [0, 2]] * np.ones((batch, 1))
                        for f, q in zip(hand.fingers, angles, strict=True)], axis=1)
    spec = g.GraspSpec()
    got = g.hand_quality(field, poses, centres, hand.fingers, angles, 0.4, spec)
    radii = np.array([f.radius for f in hand.fingers])
    points, normals = contacts(field, poses, centres, radii)
    directions = g.force_vertices(normals, spec.mu, np.ones((batch, n, 3)))
    spatial = np.stack([directions[..., 0], np.zeros((batch, n, 3)), directions[..., 1]],
                       axis=-1)
    limits = np.array([[kin.max_tip_force(f, q[b] if q.ndim == 2 else q, 0.4, spatial[b, i])
                        for i, (f, q) in enumerate(zip(hand.fingers, angles, strict=True))]
                       for b in range(batch)])  # (batch, n, 3), one joint vector at a time
    reference = g.quality(points, poses[:, :2], directions * limits.reshape(batch, n, 3, 1),
                          field.contour.max_radius, spec.load)
    np.testing.assert_allclose(got, reference, rtol=1e-12, atol=1e-12)
    assert np.ptp(got) > 0.1  # the batch spans weak and strong grasps


@pytest.mark.parametrize("name", ["two-finger", "three-finger"])
def test_tilted_quality_is_the_best_or_least_with_each_normal_turned_either_way(name):
    """`tilt`: the most the grasp could have in a world whose outline turns each contact's
    normal by up to that much - the best of the model's normals and of every finger's
    turned by -tilt or +tilt, each way composed as the untilted quality is."""
    hand = load_hand(name)
    field = contact_field(preset_object("blob:3"))
    rng = np.random.default_rng(5)
    batch, n, tilt = 8, len(hand.fingers), np.deg2rad(2.4)
    poses = np.column_stack([rng.normal(0, 0.002, (batch, 2)), rng.uniform(-np.pi, np.pi,
                                                                            batch)])
    angles = [np.array(f.home) for f in hand.fingers]
    centres = np.broadcast_to(np.stack([kin.forward(f, q)[[0, 2]] for f, q in
                                        zip(hand.fingers, angles, strict=True)]),
                              (batch, n, 2)).copy()
    spec = g.GraspSpec()
    got = g.hand_quality(field, poses, centres, hand.fingers, angles, 0.4, spec, tilt)
    plain = g.hand_quality(field, poses, centres, hand.fingers, angles, 0.4, spec)
    radii = np.array([f.radius for f in hand.fingers])
    points, normals = contacts(field, poses, centres, radii)
    ways = []
    for signs in itertools.product((-1.0, 1.0), repeat=n):
        turn = tilt * np.array(signs)
        c, s = np.cos(turn), np.sin(turn)
        turned = np.stack([c * normals[..., 0] - s * normals[..., 1],
                           s * normals[..., 0] + c * normals[..., 1]], axis=-1)
        directions = g.force_vertices(turned, spec.mu, np.ones((batch, n, 3)))
        spatial = np.stack([directions[..., 0], np.zeros((batch, n, 3)),
                            directions[..., 1]], axis=-1)
        limits = np.array([[kin.max_tip_force(f, q, 0.4, spatial[b, i]) for i, (f, q) in
                            enumerate(zip(hand.fingers, angles, strict=True))]
                           for b in range(batch)])
        ways.append(g.quality(points, poses[:, :2], directions * limits[..., None],
                              field.contour.max_radius, spec.load))
    np.testing.assert_allclose(got, np.max([plain, *ways], axis=0), rtol=1e-9, atol=1e-12)
    assert np.all(got >= plain) and np.any(got > plain + 0.01)
    # `least`: the worst of the same ways, what the gate's check near the margin fears
    worst = g.hand_quality(field, poses, centres, hand.fingers, angles, 0.4, spec, tilt,
                           least=True)
    np.testing.assert_allclose(worst, np.min([plain, *ways], axis=0), rtol=1e-9, atol=1e-12)
    assert np.all(worst <= plain) and np.any(worst < plain - 0.01)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"mu": 0}, "mu must be > 0"),
    ({"mass_kg": -1}, "mass must be >= 0"),
    ({"margin_n": 0.5, "threshold_n": 0.3}, "must be at least the disturbance margin"),
    ({"threshold_n": 3.0, "start_n": 2.0},
     r"start grasp quality \(2.0 N\) must be at least the threshold \(3.0 N\)"),
    ({"start_n": float("nan")}, "start grasp quality"),
    # a held-out lab's: "threshold (inf N) must be at least the disturbance margin (0.2 N)"
    ({"threshold_n": float("inf")}, "threshold must be a finite number, got inf"),
    ({"mass_kg": float("inf")}, "mass must be a finite number, got inf"),
    ({"mu": float("nan")}, "mu must be a finite number, got nan"),
])
def test_spec_validation(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        g.GraspSpec(**kwargs)


def every_pair_reference(points, origin, forces, rho, load):
    """The quality as first written: the least gap over the normals of every pair of corner
    differences of every contact's wrench polygon (a superset of the facet normals)."""
    corners = g.wrenches(points[:, None, :], forces, origin, rho)  # (n, k, 3)
    polygons = [np.vstack([np.zeros(3), c]) for c in corners]
    edges = np.array([p[c] - p[a] for p in polygons
                      for a, c in itertools.combinations(range(len(p)), 2)])
    i, j = np.triu_indices(len(edges), 1)
    u = np.cross(edges[i], edges[j])
    norm = np.linalg.norm(u, axis=1)
    u = u[norm >= 1e-12] / norm[norm >= 1e-12, None]
    dots = np.stack([u @ p[1:].T for p in polygons])  # (n, candidates, k)
    up = np.maximum(dots.max(axis=2), 0).sum(axis=0)
    down = np.maximum(-dots.min(axis=2), 0).sum(axis=0)
    return min(np.min(up - u @ load), np.min(down + u @ load))


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 4), mu=st.floats(0.1, 1.2))
@settings(max_examples=40, deadline=None)
def test_quality_equals_the_every_pair_formulation(seed, n, mu):
    """The facet normals tried first (each plane, pairs of edges of two polygons) give the
    value every pair of corner differences gave, inside the sum and outside it."""
    rng = np.random.default_rng(seed)
    points, normals = on_disc(rng.uniform(0, 360, n), rng.uniform(0.02, 0.03, (n, 1)))
    limits = rng.uniform(0.3, 4, (n, 3))
    limits[rng.uniform(size=n) < 0.2, 1] *= 0.8  # straight in within the cone edges' chord
    forces = g.force_vertices(normals, mu, limits)
    origin = rng.normal(0, 0.002, 2)
    load = rng.normal([0, 0.5, 0], [0.3, 0.5, 0.2])
    q = float(g.quality(points, origin, forces, 0.03, load))
    assert q == pytest.approx(every_pair_reference(points, origin, forces, 0.03, load),
                              rel=1e-9, abs=1e-12)
