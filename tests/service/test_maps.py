"""Map presets and file loaders."""

import re
import warnings

import numpy as np
import pytest

from service.errors import MapError
from service.localization.maps import check_map_spec, load_map, load_rows, peaks


def test_peaks_matches_the_benchmark_definition():
    m = peaks()
    assert m.shape == (201, 201)
    assert m.spacing == pytest.approx(0.001)
    assert m.extent == pytest.approx((0.2, 0.2))
    # MATLAB's peaks(3) centre value is 0.981; the grid centre is (0, 0).
    z0 = 3 * np.exp(-1) - 1 / 3 * np.exp(-1)
    assert m.heights[100, 100] == pytest.approx(z0 * 0.01)


def test_bumps_is_seeded_and_sized():
    a, b, c = load_map("bumps:40:1"), load_map("bumps:40:1"), load_map("bumps:40:2")
    assert a.shape == (401, 401)
    np.testing.assert_array_equal(a.heights, b.heights)
    assert not np.array_equal(a.heights, c.heights)


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".txt"])
def test_user_files_load(tmp_path, suffix):
    grid = np.random.default_rng(0).normal(0, 0.001, (6, 9))
    path = tmp_path / f"surface{suffix}"
    if suffix == ".npy":
        np.save(path, grid)
    else:
        np.savetxt(path, grid, delimiter="," if suffix == ".csv" else " ")
    m = load_map(str(path), spacing=0.002)
    assert m.shape == (6, 9) and m.spacing == 0.002
    np.testing.assert_allclose(m.heights, grid)


@pytest.mark.parametrize("spec, spacing, message", [
    ("nosuch", None, "unknown map preset"),
    ("bumps:x", None, "must be numbers"),
    ("missing.npy", 0.001, "does not exist"),
    ("peaks", 0.001, "applies to map files"),
])
def test_bad_map_specs(spec, spacing, message):
    with pytest.raises(MapError, match=message):
        load_map(spec, spacing)


def test_a_path_that_is_no_regular_file_is_called_so(tmp_path):
    """A directory or a FIFO named as a map was said not to exist."""
    folder = tmp_path / "maps.npy"
    folder.mkdir()
    with pytest.raises(MapError, match="is not a regular file"):
        load_map(str(folder), 0.001)
    with pytest.raises(MapError, match="a map file is a grid of heights"):
        load_map(str(tmp_path / "heights.npz"), 0.001)  # it was called a preset


def test_file_needs_spacing(tmp_path):
    path = tmp_path / "s.npy"
    np.save(path, np.zeros((3, 3)))
    with pytest.raises(MapError, match="needs its sample spacing .*--spacing.*scenario.spacing"):
        load_map(str(path))


def test_unreadable_and_pickled_files_are_rejected(tmp_path):
    """Each says how to write a file that loads; none passes on NumPy's advice to load a
    pickle (`allow_pickle=`) or to pick columns (`usecols`), as a fault campaign found."""
    garbage = tmp_path / "g.npy"
    garbage.write_bytes(b"not a numpy file at all")
    pickled = tmp_path / "p.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    ragged = tmp_path / "r.csv"
    ragged.write_text("1,2,3\n4,5\n")
    for path, how in [(garbage, "numpy.save"), (pickled, "numpy.save"),
                      (ragged, "same count of numbers, separated by commas")]:
        with pytest.raises(MapError, match="is not a") as refused:
            load_map(str(path), 0.001)
        assert how in str(refused.value)
        assert "allow_pickle" not in str(refused.value) and "usecols" not in str(refused.value)


def test_a_text_grid_that_does_not_parse_is_told_plainly(tmp_path):
    """A researcher's findings: an empty CSV leaked NumPy's warning and was called a grid
    of 0x1 samples; a semicolon-separated one was cut mid-value; a header row was "row 0,
    column 1"."""
    empty, semi, header = tmp_path / "e.csv", tmp_path / "s.csv", tmp_path / "h.csv"
    empty.write_text("")
    semi.write_text("0.1;0.2\n0.3;0.4\n")
    header.write_text("x,y\n1,2\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for path, words in [(empty, "the file holds no numbers"),
                            (semi, "'0.1;0.2' to float64 in data row 1, column 1"),
                            (header, "'x' to float64 in data row 1, column 1")]:
            with pytest.raises(MapError, match=re.escape(words)) as refused:
                load_map(str(path), 0.001)
            assert "not semicolons" in str(refused.value)


def test_a_spreadsheets_csv_with_a_byte_order_mark_loads(tmp_path):
    """A held-out CSV saved by a spreadsheet as "UTF-8 with BOM" was refused: "could not
    convert string '\\ufeff-6.42e-12'"; outlines share the reader."""
    grid = np.arange(12, dtype=float).reshape(3, 4) * 1e-4
    text = "\n".join(",".join(repr(float(v)) for v in row) for row in grid)
    (tmp_path / "bom.csv").write_bytes("\ufeff".encode() + text.encode())
    np.testing.assert_array_equal(load_map(str(tmp_path / "bom.csv"), spacing=0.001).heights,
                                  grid)
    (tmp_path / "named.csv").write_bytes("\ufeffx,z\n0,0\n0.04,0\n0.04,0.04\n".encode())
    assert load_rows(tmp_path / "named.csv", ",", header=True).shape == (3, 2)


def test_a_non_finite_height_is_found_for_the_lab(tmp_path):
    """"has 1 non-finite heights" named neither where nor in good grammar."""
    grid = np.zeros((5, 6))
    grid[3, 2] = np.nan
    np.save(tmp_path / "hole.npy", grid)
    with pytest.raises(MapError, match=r"has 1 non-finite height \(NaN or inf\), the first in "
                                       r"row 3, column 2 \(counting from 0\)"):
        load_map(str(tmp_path / "hole.npy"), spacing=0.001)


def test_a_campaigns_spacing_is_named_where_a_map_needs_one():
    """A held-out check's campaign on a map file without a spacing was told of
    `--spacing`, `scenario.spacing` and `set_map`, not of the campaign's own key."""
    with pytest.raises(MapError, match="or in a campaign file"):
        check_map_spec("heights.npy", None)
    with pytest.raises(MapError, match="a campaign's `spacing`"):
        check_map_spec("peaks", 0.001)


def test_a_npy_header_is_checked_before_the_array_is_read(tmp_path):
    """A held-out check's 928-byte .npy whose header claimed 100000 x 100000 samples was a
    MemoryError of 74.5 GiB in every command that loads a map, and an `internal` error in
    hapticd."""
    liar = tmp_path / "liar.npy"
    with open(liar, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False,
                                                 "shape": (100_000, 100_000)})
        f.write(b"\0" * 800)
    with pytest.raises(MapError, match=r"is 100000 x 100000 samples \(at most 16,000,000\)"):
        load_map(str(liar), 0.001)
    short = tmp_path / "short.npy"
    np.save(short, np.zeros((60, 60)))
    short.write_bytes(short.read_bytes()[:-8])
    with pytest.raises(MapError, match="is cut short: its header promises 60 x 60 samples"):
        load_map(str(short), 0.001)
    empty = tmp_path / "zero_rows.npy"
    np.save(empty, np.zeros((0, 60)))
    with pytest.raises(MapError, match=r"holds no samples \(0 rows of 60\)"):
        load_map(str(empty), 0.001)


def test_a_map_file_it_may_not_read_is_told_so(tmp_path, monkeypatch):
    """A held-out check's unreadable .npy (mode 000, read by another user) was "not a NumPy
    array of numbers ... holds objects"."""
    from service.localization import maps

    def refused(path, spec):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(maps, "_read_npy", refused)
    path = tmp_path / "locked.npy"
    np.save(path, np.zeros((4, 4)))
    with pytest.raises(MapError, match="cannot be read: permission denied"):
        load_map(str(path), 0.001)


def test_heights_no_unit_explains_are_refused(tmp_path):
    """A held-out check's heights near 1e298: a dozen NumPy overflow warnings, 300-digit
    heights and the advice to divide them by a million."""
    path = tmp_path / "big.npy"
    np.save(path, np.full((20, 20), 1e298))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not one NumPy warning on the way
        with pytest.raises(MapError, match="heights up to 1e\\+298: heights are metres"):
            load_map(str(path), 0.001)
