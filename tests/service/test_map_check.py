"""Map checks on load: what a map offers a fingertip, and the warnings and refusals."""

import warnings

import numpy as np
import pytest

from service.errors import MapError
from service.localization.localizers.symmetry import LATTICE
from service.localization.map_check import (
    check_map,
    image_differences,
    profile_symmetries,
    profile_symmetry_matches,
)
from service.localization.maps import load_map
from service.localization.surface import HeightMap, contact_surface

MM_WARNING = "look like millimetres"


def warned(report, text: str) -> bool:
    return any(text in w for w in report.warnings)


@pytest.mark.parametrize("spec", ["peaks", "bumps:20:1", "plate:20:0", "pattern:20:1",
                                  "shell:20:2", "terrain:20:3", "profile:plate:20:4",
                                  "profile:smooth:20:0"])
def test_maps_in_metres_do_not_warn_of_millimetres_and_in_millimetres_do(spec):
    m = load_map(spec)
    assert not warned(check_map(m, 0.008), MM_WARNING)
    in_mm = HeightMap(m.heights * 1000, m.spacing, name="mm")
    assert warned(check_map(in_mm, 0.008), MM_WARNING)


def test_a_whole_map_in_millimetres_warns_about_the_spacing():
    m = load_map("bumps:20:1")
    report = check_map(HeightMap(m.heights * 1000, 1.0), 0.008)
    assert warned(report, MM_WARNING) and warned(report, "--spacing in millimetres")
    assert warned(report, "spans under two samples")


def test_a_map_in_micrometres_is_told_so():
    """A held-out scan in integer micrometres was told "they look like millimetres ...
    divide them by 1000", which left them a thousand times too high."""
    m = load_map("bumps:20:1")
    report = check_map(HeightMap(m.heights * 1e6, m.spacing, name="um"), 0.008)
    assert warned(report, "look like micrometres") and warned(report, "1,000,000")
    assert not warned(report, MM_WARNING)


def test_a_map_too_small_for_the_step_is_told_before_a_run_refuses_it():
    """A held-out 30 mm map passed `haptic map check`, and every `haptic run --noise` on it
    was refused: starts are drawn two steps inside every edge."""
    small = HeightMap(np.random.default_rng(0).normal(size=(31, 31)) * 1e-3, 0.001,
                      name="small")
    assert warned(check_map(small, 0.008, step=0.01), "too small for a step of 10 mm")
    assert not warned(check_map(small, 0.002, step=0.005), "too small for a step")


@pytest.mark.parametrize("radius, message", [(0.3, "does not fit"), (8.0, "give 0.008")])
def test_a_radius_the_map_cannot_take_is_refused(radius, message):
    with pytest.raises(MapError, match=message):
        check_map(load_map("peaks"), radius)


def test_a_tip_too_many_samples_wide_is_refused_before_any_work():
    fine = HeightMap(np.zeros((2001, 2001)), 0.0001, name="fine")
    with pytest.raises(MapError, match="resample it to a spacing of 1 mm or coarser"):
        contact_surface(fine, 0.008)
    # a map too large at a spacing already coarse enough for the tip: the advice is a spacing
    # it does not have yet (it said "about 1 mm is plenty" of a map at 1 mm)
    large = HeightMap(np.zeros((6000, 6000)), 0.001, name="large")
    with pytest.raises(MapError, match=r"crop the map, or resample it to a spacing of 1.01 mm"):
        contact_surface(large, 0.008)


def test_plains_features_and_hidden_pits():
    z = np.zeros((201, 201))
    z[:, 98:102] = -0.005  # a slot 4 mm wide, 5 mm deep: narrower than an 8 mm tip
    report = check_map(HeightMap(z, 0.001, name="slot"), 0.008)
    assert report.smallest_feature is not None and report.smallest_feature <= 0.004
    assert report.hidden_depth > 0.004 and 0.01 < report.hidden_share < 0.05
    assert report.plains_share > 0.8 and warned(report, "plain")
    tilted = HeightMap(np.tile(np.arange(201) * 0.0002, (201, 1)), 0.001, name="tilt")
    flat = check_map(tilted, 0.008)
    assert flat.smallest_feature is None and flat.hidden_share == 0
    assert flat.steepest_slope == pytest.approx(0.2)
    # a tilted plane is no feature, but it is not flat either (a helper's 3 mm texture
    # was reported "none (flat)")
    assert "smallest none as steep as 1 in 4" in "\n".join(flat.lines())
    level = check_map(HeightMap(np.zeros((201, 201)), 0.001, name="level"), 0.008)
    assert "smallest none (flat)" in "\n".join(level.lines())
    # every motion maps a flat map onto itself (a held-out check read "none found")
    assert "symmetries every motion (the map is flat" in "\n".join(level.lines())


def test_symmetries_of_surfaces_and_profiles():
    assert len(check_map(load_map("eggcrate"), 0.008).symmetries) > 10
    assert len(check_map(load_map("bumps:20:1"), 0.008).symmetries) == 0
    x = np.arange(301) * 0.001
    bump = np.exp(-((x - 0.15) / 0.02) ** 2) * 0.01  # mirror-symmetric about its middle
    motions = profile_symmetries(bump, 0.001)
    assert len(motions) >= 1 and motions[0][0] == 2
    periodic = np.sin(2 * np.pi * x / 0.05) * 0.005
    shifts = profile_symmetries(periodic, 0.001)
    assert any(k == 0 and abs(abs(dx) - 0.05) < 0.002 for k, dx, _ in shifts)
    rng = np.random.default_rng(0)
    from scipy import ndimage

    rough = ndimage.gaussian_filter1d(rng.standard_normal(301), 10)
    assert len(profile_symmetries(rough, 0.001)) == 0


def _staircase(rows: int, tread: int, rise: float, seed: int) -> np.ndarray:
    """Heights (rows, 4 treads) at 1 mm: each tread `rise` above the last and carrying the
    same random bumps (random along y)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    tile = ndimage.gaussian_filter(rng.standard_normal((rows, tread)), 4, mode="wrap")
    tile *= 0.003 / np.ptp(tile)
    return np.tile(tile, (1, 4)) + rise * np.repeat(np.arange(4), tread)[None, :]


def test_a_symmetry_up_to_a_height_change_is_found():
    """A finger reads heights relative to its start, so a copy of the surface a constant
    height above another reads the same: a staircase's treads alike but for their height
    (a held-out check: the map check named only shifts along the treads' width, which the
    stairs' rise hid among, and not the shift by one tread)."""
    stairs = _staircase(120, 40, 0.004, seed=1)
    shifts = check_map(HeightMap(stairs, 0.001, name="stairs"), 0.008).aligned_symmetries
    assert any(k == 0 and abs(abs(dx) - 0.040) < 0.002 and abs(dy) < 0.002
               for k, dx, dy in shifts)
    profile = profile_symmetries(stairs[60], 0.001)
    assert any(k == 0 and abs(abs(dx) - 0.040) < 0.002 for k, dx, _ in profile)


def test_a_flat_profile_like_a_flat_map_has_no_symmetry():
    """A held-out check: a flat profile listed hundreds of motions (its rounding error
    correlated with itself) where a flat map listed none; the plains line says what
    matters."""
    for heights in (np.full((1, 701), 0.02), np.full((80, 80), 0.02)):
        report = check_map(HeightMap(heights, 0.001, name="flat"), 0.008)
        assert len(report.symmetries) == 0
        text = "\n".join(report.lines())
        along = "its length" if report.is_profile else "the area"
        assert "symmetries every motion (the map is flat" in text
        assert f"plains     100.0% of {along}" in text
    assert len(profile_symmetries(np.full(701, 0.02) + 3e-4 * (np.arange(701) == 350),
                                  0.001)) >= 1  # a bump 0.3 mm tall on it: a reversal


def test_report_lines_and_json_say_everything():
    report = check_map(load_map("pattern:20:3"), 0.008)
    text = "\n".join(report.lines())
    for word in ("heights", "slope", "features", "hidden", "plains", "symmetries"):
        assert word in text
    data = report.to_json()
    assert data["radius"] == 0.008 and len(data["height_range"]) == 2


def test_a_symmetry_is_reported_with_how_well_and_where_it_holds(plate_map):
    """The helper's machined plate was said to repeat under three motions "within 3 %",
    though only its rectangular pocket does (its bosses and slot do not): each motion now
    comes with its correlation and the share of the map its image overlaps."""
    plate = check_map(load_map(str(plate_map), spacing=0.001), 0.008)
    assert len(plate.symmetries) == len(plate.symmetry_strengths) > 0
    corr, overlap = plate.symmetry_strengths.T
    assert np.all(corr >= LATTICE[0]) and np.all(overlap < 0.6)  # the bar of the search
    text = "\n".join(plate.lines())
    assert "within 3 %" not in text
    assert f"over {overlap[0]:.0%} of the map" in text
    crate = check_map(load_map("eggcrate"), 0.008)
    corr, overlap = crate.symmetry_strengths[0]
    assert corr > 0.99 and overlap > 0.99  # a periodic crate repeats everywhere
    payload = plate.to_json()
    assert len(payload["symmetry_correlation"]) == len(payload["symmetries"])
    ramp = np.linspace(0, 0.01, 301)
    mirrored = np.concatenate([ramp, ramp[::-1]])
    found = profile_symmetry_matches(mirrored, 0.001)
    assert found[0][0] == 2 and found[0][3] > 0.99 and found[0][4] == 1.0


@pytest.mark.parametrize("roughness", [0.0, 2e-6])
def test_a_plate_with_one_hole_turns_about_the_hole_and_a_flat_map_about_nothing(roughness):
    """Two plains correlate perfectly: turned copies of a plate that missed its one hole
    named an axis of revolution at (156, 86) mm, and a flat map "every turn about" an
    arbitrary point."""
    x = np.arange(201) * 0.001
    xx, yy = np.meshgrid(x, x)
    rough = np.random.default_rng(4).normal(0.0, roughness, xx.shape)
    hole = np.where(np.hypot(xx - 0.06, yy - 0.13) < 0.012, -0.005, 0.0) + rough
    text = "\n".join(check_map(HeightMap(hole, 0.001, "hole"), 0.008).lines())
    assert "every turn about (60, 130) mm" in text, text
    flat = check_map(HeightMap(rough, 0.001, "flat"), 0.008)
    assert len(flat.symmetries) == 0 and "symmetries every motion (the map is flat" in \
        "\n".join(flat.lines())


def test_a_surface_of_revolution_is_named_with_its_axis(rings_map):
    """Rings repeat under every turn about their axis: the report says so, and where the axis
    lies, rather than listing three of 179 turns as if they were all."""
    text = "\n".join(check_map(load_map(str(rings_map), spacing=0.001), 0.008).lines())
    assert "surface of revolution" in text and "every turn about (110, 95) mm" in text
    assert "surface of revolution" not in "\n".join(check_map(load_map("peaks"), 0.008).lines())


def test_a_symmetry_says_whether_it_is_exact_or_broken_and_where():
    """A correlation cannot tell an exact symmetry from one a feature breaks, nor a square
    boss's 45-degree turn from a ring's: `haptic map check` said "correlation 0.94" of a
    plate whose one chamfered corner tells its quarter turns apart, and called a plate with
    a square boss "a surface of revolution" with no word of the boss's corners. Each motion
    now says how much of the map its image differs on, by how much, and where most."""
    crate = check_map(load_map("eggcrate"), 0.008)
    half = _row(crate.symmetries, 2)
    share, largest = crate.symmetry_differences[half, :2]
    assert share == 0 and largest <= 2e-4  # a periodic crate's half turn is exact
    assert "half turn (correlation 1.00 over 100% of the map; the same within 0.2 mm " \
           "throughout)" in "\n".join(crate.lines())

    pattern = check_map(load_map("pattern:20:1"), 0.008)  # four alike pockets, one chamfer
    quarter = _row(pattern.symmetries, 1)
    share, largest, x, y, x_to, y_to = pattern.symmetry_differences[quarter]
    assert 0 < share < 0.02 and largest > 0.01  # only at a corner: the plate's whole rise
    corners = [(p, q) for p, q in ((x, y), (x_to, y_to)) if min(p, 0.2 - p) < 0.02
               and min(q, 0.2 - q) < 0.02]
    assert len(corners) == 2  # a corner and the corner the quarter turn brings it to
    assert (f"quarter turn (correlation {pattern.symmetry_strengths[quarter, 0]:.2f} over "
            f"100% of the map; the same within 0.2 mm but over {share:.1%} of it, by up to "
            f"{largest * 1e3:.2f} mm, most between ({x * 1e3:.0f}, {y * 1e3:.0f}) and "
            f"({x_to * 1e3:.0f}, {y_to * 1e3:.0f}) mm)"
            ) in "\n".join(pattern.lines())  # its three quarter turns are all it has: shown

    x = np.arange(201) * 0.001
    xx, yy = np.meshgrid(x, x)
    boss = np.where((np.abs(xx - 0.1) < 0.02) & (np.abs(yy - 0.1) < 0.02), 0.004, 0.0)
    square = check_map(HeightMap(boss, 0.001, "square boss"), 0.008)
    text = "\n".join(square.lines())
    assert "surface of revolution" in text
    assert "turned copies not the same within 0.2 mm over" in text
    assert "by up to 4.00 mm): a surface of revolution" in text  # the boss's corners

    tilted = contact_surface(HeightMap(0.05 * xx, 0.001, "tilted plane"), 0.008)
    shifted = image_differences(tilted, np.array([[0.0, 0.03, 0.02]]))[0]
    assert shifted[0] == 0 and shifted[1] < 1e-9  # a slope under a shift is an offset
    payload = check_map(HeightMap(boss, 0.001, "square boss"), 0.008).to_json()
    assert len(payload["symmetry_differ_share"]) == len(payload["symmetries"]) \
        == len(payload["symmetry_differ_by"]) == len(payload["symmetry_differ_at"])
    assert np.shape(payload["symmetry_differ_at"][0]) == (2, 2)  # a place and its image
    narrow = check_map(HeightMap(np.tile(np.sin(np.arange(12) * 0.5) * 1e-3, (12, 1)),
                                 0.001, "narrow"), 0.005)  # no sample a tip's radius in
    unmeasured = narrow.to_json()["symmetry_differ_share"]
    assert len(unmeasured) > 0 and all(v is None for v in unmeasured)  # JSON has no NaN


def _row(motions: np.ndarray, quarter_turns: int) -> int:
    """The row of `motions` that turns by `quarter_turns` with no shift."""
    return int(np.flatnonzero((motions[:, 0] == quarter_turns)
                              & (np.abs(motions[:, 1:]) < 1e-9).all(axis=1))[0])


def test_plains_on_a_tilted_map_count_as_on_a_level_one():
    """A plate scanned 3 degrees off level was reported 0 % plain (a step reads its slope,
    0.5 mm), the same plate level 88 %; on either a step tells the finger nothing of where
    it is, and the tilted one gave no warning."""
    x = np.arange(201) * 0.001
    xx, yy = np.meshgrid(x, x)
    boss = np.where((np.abs(xx - 0.1) < 0.02) & (np.abs(yy - 0.1) < 0.02), 0.004, 0.0)
    level = check_map(HeightMap(boss, 0.001, "level plate"), 0.008)
    tilted = check_map(HeightMap(boss + 0.05 * xx + 0.02 * yy, 0.001, "tilted plate"), 0.008)
    assert level.plains_share > 0.8 and warned(level, "plain")
    assert tilted.plains_share == pytest.approx(level.plains_share, abs=0.02)
    assert warned(tilted, "plain")
    assert tilted.tilt == pytest.approx((0.05, 0.02), abs=1e-3) and level.tilt == (0.0, 0.0)
    plains_line = next(line for line in tilted.lines() if line.startswith("plains"))
    assert "more than the map's overall tilt would (3.1 deg, rising toward 22 deg" in plains_line
    assert "overall tilt" not in "\n".join(level.lines())
    assert tilted.to_json()["tilt"] == pytest.approx([0.05, 0.02], abs=1e-3)
    ramp = check_map(HeightMap(0.02 * xx[:1], 0.001, "sloped profile"), 0.008)
    assert "100.0% of its length" in "\n".join(ramp.lines())
    assert "overall tilt would (1.1 deg, rising along it)" in "\n".join(ramp.lines())
    curved = check_map(load_map("shell:20:0"), 0.008)  # sloped everywhere, evenly nowhere
    assert curved.tilt == (0.0, 0.0) and curved.plains_share < 0.01
    # a held-out check's: a plane 0.6 degrees off level was 10 % plain (a 10 mm step reads
    # 0.1 mm, but the window spans two steps), one at 1 degree 2 %; and a 5-degree plane
    # rising at 45 degrees to the axes was "steepest 3.5 deg"
    for degrees in (0.6, 1.0):
        plane = check_map(HeightMap(np.tan(np.radians(degrees)) * xx, 0.001, "plane"), 0.008)
        assert plane.plains_share == 1.0 and plane.tilt[0] > 0
    diagonal = check_map(HeightMap(np.tan(np.radians(5.0)) * (xx + yy) / np.sqrt(2), 0.001,
                                   "diagonal"), 0.008)
    assert np.degrees(np.arctan(diagonal.steepest_slope)) == pytest.approx(5.0, abs=0.05)


def test_a_tip_wider_than_the_map_is_warned_of():
    """A held-out check's: a 240 mm tip on a 200 mm map was taken without a word, though
    every contact height then rests on ground the map does not have."""
    z = np.zeros((201, 201))
    z[90:110, 90:110] = 0.004
    wide = check_map(HeightMap(z, 0.001, "plate"), 0.12)
    assert warned(wide, "the tip (240 mm across) is wider than the map (200 mm)")
    assert not warned(check_map(HeightMap(z, 0.001, "plate"), 0.008), "wider than the map")


def test_a_wall_is_not_called_smooth_ground():
    """A held-out check: a profile with a 20 mm vertical wall (steepest 87 degrees) was
    "smallest none as steep as 1 in 4 for its width: smooth, gently varying ground"."""
    x = np.arange(201) * 0.001
    wall = HeightMap((0.01 + 0.02 * (x > 0.1) + 0.002 * np.sin(x / 0.02))[None], 0.001,
                     name="wall")
    report = check_map(wall, 0.008, 0.01)
    features = next(line for line in report.lines() if line.startswith("features"))
    assert report.smallest_feature is None and "steps or walls" in features
    assert "smooth" not in features
    gentle = HeightMap((0.01 + 0.002 * np.sin(x / 0.02))[None], 0.001, name="gentle")
    assert "smooth, gently varying ground" in next(
        line for line in check_map(gentle, 0.008, 0.01).lines() if line.startswith("features"))


def test_an_exact_symmetry_found_on_a_coarse_grid_reads_exact():
    """A held-out helper's map, a terrain beside its own half-turned copy (400 x 200 mm, the
    same under a half turn to 1e-17 m), read "half turn then shift (+0, -3) mm ... the same
    within 0.2 mm but over 65.7% of it, by up to 1.79 mm": the motion is found on a grid of
    about 160 samples across (3 mm here), and measured there. Aligned at full resolution,
    it is exact; a copy with a 0.3 mm bump names the bump."""
    h = np.asarray(load_map("terrain:20:1").heights)
    twin = np.hstack([h, np.full((h.shape[0], 20), h.mean()), h[::-1, ::-1]])
    report = check_map(HeightMap(twin, 0.001, "twin"), 0.008)
    text = "\n".join(report.lines())
    assert "half turn (correlation" in text and "the same within 0.2 mm throughout" in text
    copy = np.hstack([h, np.full((h.shape[0], 20), h.mean()), h])
    xx, yy = np.meshgrid(np.arange(copy.shape[1]) * 0.001, np.arange(copy.shape[0]) * 0.001)
    copy = copy + 0.0006 * np.exp(-((xx - 0.32) ** 2 + (yy - 0.1) ** 2) / (2 * 0.005 ** 2))
    share, largest, x, y, x_to, y_to = check_map(HeightMap(copy, 0.001, "copy"), 0.008
                                                 ).symmetry_differences[0]
    assert 0 < share < 0.01 and largest > 0.2e-3
    assert min(np.hypot(x - 0.32, y - 0.1), np.hypot(x_to - 0.32, y_to - 0.1)) < 0.005


def test_a_step_shorter_than_a_sample_does_not_make_the_map_plain():
    """`haptic map check peaks --step 0.0005` said "plains 100.0%" (the window about each
    point was the point alone), the same map 7 % at a 10 mm step."""
    short = check_map(load_map("peaks"), 0.008, 0.0005).plains_share
    assert short < 0.2
    assert check_map(load_map("peaks"), 0.008, 0.001).plains_share == pytest.approx(short)


def test_a_boss_on_a_profile_is_a_feature_of_its_own_width():
    """A held-out check: a row through a boss 3 mm high and 9 mm wide (steeper than 1 in 4
    for its width) was "no bump or pit as steep as 1 in 4": the windows doubled from 9 to
    17 samples, and 17 mm asks a bump for 4.25 mm."""
    z = np.full(200, 0.010)
    z[136:145] = 0.013
    report = check_map(HeightMap(z[None], 0.001, name="boss"), 0.008)
    assert report.smallest_feature == pytest.approx(0.010)
    assert "smallest 10 mm across" in "\n".join(report.lines())


def test_a_strip_narrower_than_the_tip_is_checked_without_numpy_warnings() -> None:
    """A held-out 12 mm strip of ridges: its symmetries were aligned over no place the tip
    fits, and numpy's "Mean of empty slice" was printed around the report."""
    x = np.linspace(0.0, 0.2, 201)
    strip = HeightMap(np.tile(0.003 * np.sin(2 * np.pi * x / 0.025), (12, 1)), 0.001,
                      name="strip")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lines = check_map(strip, 0.008, 0.01).lines()
    assert any("wider than the map" in line for line in lines)
