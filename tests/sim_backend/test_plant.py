"""The emulated finger's plant: where the surface and the map's edge put the fingertip."""

from __future__ import annotations

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.hand import load_hand
from service.localization.maps import bumps
from service.localization.surface import HeightMap
from sim_backend.emulator.plant import FingerPlant


def test_a_finger_driven_past_the_edge_slides_down_the_wall_to_the_surface():
    """Held in the air where it met the map's edge, the emulated finger once reported a
    reading 15 mm above the surface as a contact: a planar finger on the bus emulator
    then never declared (profile:smooth, seed 2)."""
    hand = load_hand("planar")
    world = HeightMap(bumps(20.0, seed=1).heights[100:101, :], 0.001, name="row")
    plant = FingerPlant(hand, world, (0.012, 0.0, 0.0))
    home = kin.forward(hand, plant.home_q)
    # up in the air 2 mm inside the edge, then driven 5 mm past it and far below
    air = kin.inverse(hand, home + np.array([-0.010, 0.0, 0.004]), plant.home_q).q
    plant._actual_q = air
    held = kin.forward(hand, air)
    assert plant.contact_height(held) < held[2]
    drive = kin.inverse(hand, home + np.array([-0.017, 0.0, -0.03]), air).q
    assert plant.contact_height(kin.forward(hand, drive)) is None  # off the map

    q, contact = plant.settle(drive)

    centre = kin.forward(hand, q)
    assert contact
    assert abs(centre[0] - held[0]) < 1e-6  # stopped at the wall
    assert abs(centre[2] - plant.contact_height(centre)) < 1e-5  # resting on the surface
