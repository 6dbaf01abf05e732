"""Height maps and the sphere-contact surface (paper Eq. 7)."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from service.errors import MapError
from service.localization.surface import HeightMap, contact_surface


def brute_force_contact(heights: np.ndarray, spacing: float, radius: float,
                        row: int, col: int) -> float:
    """Eq. 7 directly: max over the disk under the sphere of map height + sphere cap."""
    rows, cols = np.indices(heights.shape)
    d2 = ((rows - row) ** 2 + (cols - col) ** 2) * spacing**2
    under = d2 <= radius**2 + 1e-12
    return float(np.max(heights[under] + np.sqrt(np.maximum(radius**2 - d2[under], 0.0))))


def test_flat_map_lifts_centre_by_radius():
    m = HeightMap(np.zeros((30, 40)), 0.001)
    c = contact_surface(m, 0.005)
    np.testing.assert_allclose(c.centre_heights, 0.005)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), radius_samples=st.floats(1.0, 6.0))
@example(seed=0, radius_samples=1.9999999999999991)  # a disk edge sample exactly at r
def test_dilation_matches_brute_force(seed, radius_samples):
    rng = np.random.default_rng(seed)
    heights = rng.normal(0, 0.002, size=(17, 23))
    spacing = 0.001
    m = HeightMap(heights, spacing)
    radius = radius_samples * spacing
    c = contact_surface(m, radius)
    # Interior points, where the whole disk lies on the map.
    k = int(np.ceil(radius_samples))
    for row, col in [(k + 1, k + 1), (8, 11), (16 - k, 22 - k)]:
        assert c.centre_heights[row, col] == pytest.approx(
            brute_force_contact(heights, spacing, radius, row, col), abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), rows=st.integers(1, 12), cols=st.integers(2, 15),
       radius_samples=st.floats(0.5, 14.0), erode=st.booleans())
def test_the_sphere_filter_is_the_2d_grey_dilation_everywhere(seed, rows, cols,
                                                              radius_samples, erode):
    """Row by row, edges and a footprint wider than the map included: the same result as
    scipy's 2-D filter, to the last bit."""
    from scipy import ndimage

    from service.localization.surface import sphere_filter, sphere_structure

    grid = np.random.default_rng(seed).normal(0, 0.002, size=(rows, cols))
    radius = radius_samples * 0.001
    footprint, cap = sphere_structure(radius, 0.001)
    if rows == 1:
        footprint, cap = footprint[footprint.shape[0] // 2:][:1], cap[cap.shape[0] // 2:][:1]
    scipy_filter = ndimage.grey_erosion if erode else ndimage.grey_dilation
    expected = scipy_filter(grid, footprint=footprint, structure=cap, mode="nearest")
    got = sphere_filter(grid, radius, 0.001, erode=erode)
    assert np.array_equal(got, expected)


def test_a_tip_as_wide_as_the_map_builds_in_bounded_memory(tmp_path):
    """A 90 mm tip on a 101 x 101 map at 1 mm: scipy's 2-D filter wanted about 6.6 GB for
    its border offsets (a 150 mm tip on 201 x 201 was killed for memory). Built in a
    child process whose address space may grow by at most 1 GB."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import re, resource
        import numpy as np
        from service.localization.surface import HeightMap, contact_surface
        size = int(re.search(r"VmSize:\\s+(\\d+) kB", open("/proc/self/status").read())[1])
        resource.setrlimit(resource.RLIMIT_AS, ((size << 10) + (1 << 30),) * 2)
        heights = np.random.default_rng(0).normal(0, 0.002, size=(101, 101))
        c = contact_surface(HeightMap(heights, 0.001), 0.09)
        print(float(c.centre_heights.min()) >= 0.09 - 0.01)
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "True"


def test_centre_never_below_surface_plus_radius():
    rng = np.random.default_rng(1)
    m = HeightMap(rng.normal(0, 0.003, (25, 25)), 0.001)
    c = contact_surface(m, 0.004)
    assert np.all(c.centre_heights >= m.heights + 0.004 - 1e-12)


def test_contact_surface_is_cached_per_map_and_radius():
    m = HeightMap(np.zeros((5, 5)), 0.001)
    assert contact_surface(m, 0.002) is contact_surface(m, 0.002)
    assert contact_surface(m, 0.002) is not contact_surface(m, 0.003)


def test_lookup_interpolates_and_masks_outside():
    heights = np.array([[0.0, 1.0], [2.0, 3.0]])
    m = HeightMap(heights, 0.5)
    z, inside = m.lookup(np.array([0.25, 0.5, 0.6, -0.1]), np.array([0.25, 0.5, 0.0, 0.0]))
    np.testing.assert_allclose(z[:2], [1.5, 3.0])
    np.testing.assert_array_equal(inside, [True, True, False, False])


def test_non_square_map_axes():
    heights = np.arange(12.0).reshape(3, 4)  # 3 rows (y), 4 columns (x)
    m = HeightMap(heights, 1.0)
    assert m.extent == (3.0, 2.0)
    z, _ = m.lookup(np.array([3.0]), np.array([2.0]))
    assert z[0] == 11.0


def test_single_row_is_a_profile_extruded_along_y():
    m = HeightMap(np.array([0.0, 0.001, 0.0, 0.0]), 0.001)
    assert m.is_profile and m.shape == (1, 4)
    c = contact_surface(m, 0.0015)
    z_a, in_a = c.lookup(np.array([0.001]), np.array([0.0]))
    z_b, in_b = c.lookup(np.array([0.001]), np.array([5.0]))
    assert z_a == z_b and in_a[0] and in_b[0]
    assert c.centre_heights[0, 1] == pytest.approx(0.0025)


@pytest.mark.parametrize("heights, spacing, message", [
    (np.zeros((3, 3, 3)), 0.001, "3 dimensions"),
    (np.array([[np.nan, 0.0], [0.0, 0.0]]), 0.001, "non-finite"),
    (np.zeros((1, 1)), 0.001, "at least 2 samples"),
    (np.zeros((3, 3)), 0.0, "spacing"),
    (np.array([["a", "b"]]), 0.001, "must be real"),
    (np.zeros((200, 1)), 0.001, "single column .* a profile is a single row: transpose"),
])
def test_invalid_maps_are_rejected_with_the_reason(heights, spacing, message):
    with pytest.raises(MapError, match=message):
        HeightMap(heights, spacing)


def test_map_heights_are_read_only():
    m = HeightMap(np.zeros((3, 3)), 0.001)
    with pytest.raises(ValueError):
        m.heights[0, 0] = 1.0
