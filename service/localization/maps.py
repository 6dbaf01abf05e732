"""Where height maps come from: built-in presets by name (`presets/`), or a user's file."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from service.errors import MapError
from service.localization.presets import parse, preset
from service.localization.presets.classic import SAMPLES_PER_UNIT, UNIT, bumps, eggcrate, peaks
from service.localization.surface import HeightMap

__all__ = ["SAMPLES_PER_UNIT", "UNIT", "bumps", "eggcrate", "load_map", "peaks", "preset"]


MAP_FILE_SUFFIXES = frozenset({".npy", ".csv", ".txt"})
MAX_SAMPLES = 16_000_000
"""A map file of more samples (4000 x 4000) is refused, before it is read: a 4000 x 4000
map took 1.2 GB to check, and a .npy header may claim any shape (one of 928 bytes claimed
100000 x 100000, and loading it was a MemoryError of 74.5 GiB)."""
"""What makes a map spec a file rather than a preset name."""


def check_map_spec(spec: str, spacing: float | None) -> None:
    """MapError for a map spec and spacing that cannot go together, before any file is
    touched (so hapticd may tell a client, who learns nothing about the daemon's files)."""
    suffix = Path(spec).suffix.lower()
    if suffix in MAP_FILE_SUFFIXES:
        if spacing is None:
            raise MapError(f"map file '{spec}' needs its sample spacing in metres (`--spacing` "
                           "on the command line, `scenario.spacing` in hapticd's "
                           "configuration, `spacing` beside `map` in its set_map command "
                           "or in a campaign file)")
        return
    if "/" in spec or suffix[1:].isalpha():
        raise MapError(f"map file '{spec}': a map file is a grid of heights in metres, "
                       f"{', '.join(sorted(MAP_FILE_SUFFIXES))}")
    if spacing is not None:
        raise MapError("a spacing (`--spacing`, `scenario.spacing`, a campaign's `spacing`) "
                       "applies to map files, not presets")
    parse(spec)  # a preset's name, size and seed (nothing built)


def load_map(spec: str, spacing: float | None = None) -> HeightMap:
    """A preset name, or a `.npy` / `.csv` / `.txt` grid of heights in metres with `spacing`."""
    path = Path(spec)
    check_map_spec(spec, spacing)
    if path.suffix.lower() not in MAP_FILE_SUFFIXES:
        return preset(spec)
    if not path.is_file():
        raise MapError(f"map file '{spec}' is not a regular file" if path.exists()
                       else f"map file '{spec}' does not exist")
    try:
        if path.suffix.lower() == ".npy":
            heights = _read_npy(path, spec)
        else:
            delimiter = "," if path.suffix.lower() == ".csv" else None
            heights = load_rows(path, delimiter)
    except MapError:
        raise  # said already: not "unreadable"
    except PermissionError:
        raise MapError(f"map file '{spec}' cannot be read: permission denied (run as a user "
                       "who may read it, or change its permissions)") from None
    except (ValueError, OSError, EOFError) as exc:
        raise MapError(_unreadable(spec, path.suffix.lower(), exc)) from None
    return HeightMap(heights, spacing, name=path.stem)


def _read_npy(path: Path, spec: str) -> np.ndarray:
    """A .npy file's array, its header checked first: the shape it claims must fit
    `MAX_SAMPLES` and the file's size, and its type hold no objects (never unpickled).
    ValueError for a file that is no .npy."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, _, dtype = read_header(f)
        samples = int(np.prod(shape, dtype=object))
        if samples > MAX_SAMPLES:
            raise MapError(f"map file '{spec}' is {' x '.join(map(str, shape))} samples (at "
                           f"most {MAX_SAMPLES:,}): sample it more coarsely, or cut out the "
                           "part the finger explores")
        if not dtype.hasobject and f.tell() + samples * dtype.itemsize > path.stat().st_size:
            raise MapError(f"map file '{spec}' is cut short: its header promises "
                           f"{' x '.join(map(str, shape))} samples of {dtype.itemsize} "
                           "bytes, more than the file holds; write it again with "
                           "numpy.save(path, heights)")
        f.seek(0)  # the header checked, the array from the same open file
        return np.lib.format.read_array(f, allow_pickle=False)


def load_rows(path: Path, delimiter: str | None, header: bool = False) -> np.ndarray:
    """Rows of numbers (at least 2-D) from a text file, `#` starting a comment; with
    `header`, a first row of column names (`x,z`, as spreadsheets write an outline) is
    skipped (a grid of heights has none: names there mean the file is something else). A
    file with no numbers is a ValueError that says so, not NumPy's warning and an empty
    array."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        try:
            return np.loadtxt(path, delimiter=delimiter, comments="#", ndmin=2,
                              skiprows=_header_lines(path, delimiter) if header else 0,
                              encoding="utf-8-sig")  # a spreadsheet's byte-order mark
        except UserWarning:
            raise ValueError("the file holds no numbers") from None


def _header_lines(path: Path, delimiter: str | None) -> int:
    """Lines up to and including a first row of names (every cell a word, none a number),
    else 0."""
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        for index, line in enumerate(f):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            cells = [c.strip() for c in text.split(delimiter)]
            words = all(re.fullmatch(r"[A-Za-z_][\w ()\[\].-]*", c) for c in cells)
            return index + 1 if words and not any(_number(c) for c in cells) else 0
    return 0


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _unreadable(spec: str, suffix: str, exc: Exception) -> str:
    """Why a map file could not be read, and how to write one that can: NumPy's own words
    would advise loading a pickle (`allow_pickle=`) or `usecols`, neither of which helps."""
    if suffix == ".npy":
        return (f"map file '{spec}' is not a NumPy array of numbers (it is not a .npy file, "
                "or it holds objects, which are never unpickled): write one with "
                "numpy.save(path, heights), heights a 2-D float array in metres")
    sep = "commas (not semicolons or tabs)" if suffix == ".csv" else "spaces"
    return (f"map file '{spec}' is not a grid of numbers ({numpy_reason(exc)}): every row "
            f"needs the same count of numbers, separated by {sep}, heights in metres")


def numpy_reason(exc: Exception) -> str:
    """NumPy's reason a text grid did not parse: its first clause (what follows is advice
    such as `usecols`, which does not help), rows counted from 1 like its columns (NumPy
    counts the data rows from 0 and the columns from 1)."""
    text = str(exc).splitlines()[0].split("; ")[0].rstrip(". ")  # not its advice after it
    text = re.sub(r"at row (\d+), column (\d+)",
                  lambda m: f"in data row {int(m[1]) + 1}, column {m[2]}", text)
    return text if len(text) <= 160 else text[:157] + "..."
