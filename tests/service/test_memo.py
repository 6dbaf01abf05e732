"""What is computed from a map or an outline lives exactly as long as it does."""

from __future__ import annotations

import gc
import pickle
import weakref

import numpy as np

from service.localization.objects.field import contact_field
from service.localization.objects.presets import preset_object
from service.localization.surface import HeightMap, contact_surface


def _gone(ref: weakref.ref) -> bool:
    gc.collect()
    return ref() is None


def test_a_maps_contact_surface_is_made_once_and_goes_with_the_map():
    """Every map a process had used stayed in memory: the surface cache's values held their
    keys (a `haptic bench grasp` worker grew to 3.6 GB on outlines alike)."""
    height_map = HeightMap(np.random.default_rng(0).random((40, 40)) * 1e-3, 0.001)
    surface = contact_surface(height_map, 0.004)
    assert contact_surface(height_map, 0.004) is surface
    assert contact_surface(height_map, 0.003) is not surface
    ref = weakref.ref(height_map)
    del height_map, surface
    assert _gone(ref)


def test_an_outlines_field_and_points_go_with_the_outline():
    contour = preset_object("blob:3")
    field = contact_field(contour)
    assert contact_field(contour) is field
    assert contour.resampled(0.001) is contour.resampled(0.001)
    ref = weakref.ref(contour)
    del contour, field
    assert _gone(ref)


def test_a_copy_sent_to_another_process_computes_its_own():
    height_map = HeightMap(np.random.default_rng(1).random((40, 40)) * 1e-3, 0.001)
    surface = contact_surface(height_map, 0.004)
    bare = len(pickle.dumps(HeightMap(height_map.heights, height_map.spacing)))
    copy = pickle.loads(pickle.dumps(height_map))
    assert len(pickle.dumps(height_map)) <= bare + 64  # the surface stays behind
    again = contact_surface(copy, 0.004)
    assert again is not surface
    assert np.array_equal(again.centre_heights, surface.centre_heights)
