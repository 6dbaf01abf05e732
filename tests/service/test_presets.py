"""The object-like preset families: seeded, sized, in metres, and what each promises."""

import numpy as np
import pytest

from service.errors import MapError
from service.localization.map_check import check_map
from service.localization.maps import load_map
from service.localization.presets import FAMILIES, names, preset

SEEDS = range(6)


@pytest.mark.parametrize("family", FAMILIES)
def test_families_are_seeded_sized_and_in_metres(family):
    a, b, c = preset(f"{family}:20:3"), preset(f"{family}:20:3"), preset(f"{family}:20:4")
    np.testing.assert_array_equal(a.heights, b.heights)
    assert not np.array_equal(a.heights, c.heights)
    assert a.shape == (201, 201) and a.spacing == pytest.approx(0.001)
    assert preset(f"{family}:30:3").shape == (301, 301)
    for seed in SEEDS:  # relief of a lab object in metres: millimetres to a few centimetres
        relief = np.ptp(preset(f"{family}:20:{seed}").heights)
        assert 0.003 < relief < 0.08, (family, seed, relief)


@pytest.mark.parametrize("seed", SEEDS)
def test_pattern_is_symmetric_but_for_one_feature(seed):
    """A half turn about the plate's centre maps the pattern onto itself except where the
    one breaking feature is: a small area that differs by millimetres."""
    z = preset(f"pattern:20:{seed}").heights
    differs = np.abs(z - np.rot90(z, 2)) > 0.001
    assert 0.001 < differs.mean() < 0.08  # the feature and its image


@pytest.mark.parametrize("seed", SEEDS)
def test_plates_have_plains_and_features(seed):
    m = preset(f"plate:20:{seed}")
    report = check_map(m, 0.008)
    assert 0.2 < report.plains_share < 0.8
    top = np.median(m.heights)  # the plate's top face is most of the map
    assert np.any(m.heights > top + 0.002) and np.any((m.heights < top - 0.001)
                                                       & (m.heights > 0.0005))


def test_terrain_does_not_repeat_at_its_edges():
    z = preset("terrain:20:1").heights
    assert np.abs(z[:, 0] - z[:, -1]).mean() > 0.1 * z.std()


def test_profiles_are_rows_of_their_surface():
    m = preset("profile:plate:20:2")
    assert m.is_profile and m.shape == (1, 201)
    source = preset("plate:20:2").heights
    assert any(np.array_equal(m.heights[0], row) for row in source)
    smooth = preset("profile:smooth:30:1")
    assert smooth.is_profile and smooth.shape == (1, 301)
    assert not np.array_equal(smooth.heights, preset("profile:smooth:30:2").heights)


def test_every_name_loads_through_load_map():
    for name in names():
        spec = "profile:smooth" if name == "profile" else name
        assert load_map(spec).heights.size > 1


@pytest.mark.parametrize("spec, message", [
    ("profile", "needs a kind"),
    ("profile:nosuch", "unknown profile kind"),
    ("peaks:20:1", "at most a size"),
    ("plate:20:1:2", "at most a size and a seed"),
    ("plate:1", "size must be"),
    ("plate:20:-1", "seed must be"),
    ("plate:20:1.5", "must be numbers"),
    ("slab", "haptic map list"),
])
def test_bad_preset_specs(spec, message):
    with pytest.raises(MapError, match=message):
        load_map(spec)
