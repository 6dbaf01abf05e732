"""Where objects come from: a preset family member, a polygon CSV, or a mesh's cross-section.

* `NAME[:SEED]` - a preset (`presets.py`);
* `FILE.csv` - one vertex per row, `x,z` in metres, the first row repeated at the end to
  close the outline (lines starting with `#` are comments);
* `FILE.stl|.obj|.ply` - the outline where a plane cuts the mesh (trimesh). The plane is
  `x=V`, `y=V` or `z=V` (metres), or six numbers `PX,PY,PZ,NX,NY,NZ` (a point and a
  normal); by default the plane z = (the mesh's centroid z).

`units="mm"` reads a file whose coordinates are millimetres.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon
from shapely.ops import unary_union

from service.errors import ObjectError
from service.localization.maps import load_rows, numpy_reason
from service.localization.objects.contour import (
    LARGEST_EXTENT,
    SMALLEST_EXTENT,
    Contour,
    make_contour,
)
from service.localization.objects.presets import preset_name_and_seed, preset_object

MESH_SUFFIXES = {".stl", ".obj", ".ply"}
OBJECT_FILE_SUFFIXES = frozenset(MESH_SUFFIXES | {".csv"})
"""What makes an object spec a file rather than a preset name."""
UNITS = {"m": 1.0, "mm": 0.001}


def check_object_spec(spec: str, *, plane: str | None = None, units: str = "m") -> None:
    """ObjectError for an object spec, plane and units that cannot go together, or a preset
    that is not one, before any file is touched (so hapticd may refuse its own config file
    at start-up, as it does a map preset it does not know, and tell a client nothing about
    its files)."""
    if units not in UNITS:
        raise ObjectError(f"object units must be one of {', '.join(UNITS)}, got '{units}'")
    suffix = Path(spec).suffix.lower()
    if suffix not in OBJECT_FILE_SUFFIXES:
        if plane is not None:
            raise ObjectError("a plane (`--plane`, `scenario.plane`) applies to mesh files "
                              "(.stl, .obj, .ply), not presets: leave it out (in a "
                              "configure, `scenario.plane` set to nil)")
        if units != "m":
            raise ObjectError("units (`--object-units`, `scenario.object_units`) apply to "
                              "object files (.csv, .stl, .obj, .ply), not presets: presets "
                              "are in metres")
        preset_name_and_seed(spec)
    elif suffix == ".csv" and plane is not None:
        raise ObjectError("a plane (`--plane`, `scenario.plane`) applies to mesh files, "
                          "not a CSV outline: leave it out (in a configure, "
                          "`scenario.plane` set to nil)")


def load_object(spec: str, *, plane: str | None = None, units: str = "m") -> Contour:
    """A preset (`keyed:3`) or a file (see the module docstring)."""
    check_object_spec(spec, plane=plane, units=units)
    path = Path(spec)
    suffix = path.suffix.lower()
    if suffix not in OBJECT_FILE_SUFFIXES:
        return preset_object(spec)
    if not path.is_file():
        raise ObjectError(f"object file '{spec}' does not exist")
    if suffix == ".csv":
        return _csv(path, UNITS[units])
    return mesh_section(path, plane, UNITS[units])


def _csv(path: Path, scale: float) -> Contour:
    try:
        points = load_rows(path, ",", header=True)
    except (ValueError, OSError) as exc:
        raise ObjectError(f"object file '{path}' could not be read as x,z rows "
                          f"({numpy_reason(exc)}): each row needs two numbers separated by a "
                          "comma") from None
    _check_units(points, scale, path)
    return make_contour(_counter_clockwise(points) * scale, path.stem, closed=True)


def _counter_clockwise(rows: np.ndarray) -> np.ndarray:
    """A closed outline's rows (the first repeated last) run counter-clockwise, from the
    same first vertex: an outline and its reverse are one contour, vertex for vertex, so a
    seed starts the object in the same place (a held-out lab's reversed file started it
    elsewhere: the contour's own turn began a vertex on)."""
    if rows.ndim != 2 or rows.shape[1] != 2 or len(rows) < 4:
        return rows  # make_contour says what is wrong
    x, z = rows[:, 0], rows[:, 1]
    clockwise = float(np.dot(x[:-1], z[1:]) - np.dot(x[1:], z[:-1])) < 0
    return rows[::-1] if clockwise else rows


def _check_units(points: np.ndarray, scale: float, path: Path) -> None:
    """Refuse millimetres asked of coordinates that are metres already: scaled, the object
    is smaller than a fingertip, and the contour's own message ("coordinates are metres")
    contradicted the units just given."""
    span = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    if scale < 1.0 and span * scale < SMALLEST_EXTENT <= span <= LARGEST_EXTENT:
        raise ObjectError(f"object file '{path.name}' read as millimetres (--object-units "
                          f"mm, `scenario.object_units`) spans only {span * scale * 1e3:.3g} "
                          f"mm; as metres it spans {span * 1e3:.3g} mm: drop the units")


PLANE_TOUCH = 1e-6
"""Metres within which a plane lies on a mesh's outermost face: the section there is
degenerate (a box's top face "missed" while its bottom face cut)."""


def parse_plane(text: str | None, centroid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(origin, unit normal) of a cutting plane from `x=V` / `y=V` / `z=V` or six numbers."""
    if text is None:
        return np.array([0.0, 0.0, centroid[2]]), np.array([0.0, 0.0, 1.0])
    axis, eq, value = text.partition("=")
    try:
        if eq:
            index = "xyz".index(axis.strip().lower())
            origin = np.zeros(3)
            origin[index] = float(value)
            normal = np.eye(3)[index]
        else:
            numbers = [float(v) for v in text.split(",")]
            if len(numbers) != 6:
                raise ValueError
            origin, normal = np.array(numbers[:3]), np.array(numbers[3:])
    except ValueError:
        raise ObjectError(f"--plane takes x=V, y=V, z=V or PX,PY,PZ,NX,NY,NZ (metres), "
                          f"got '{text}'") from None
    length = float(np.linalg.norm(normal))
    if not (np.all(np.isfinite(origin)) and np.isfinite(length) and length > 0):
        raise ObjectError(f"--plane '{text}': the point must be finite and the normal non-zero")
    return origin, normal / length


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3): in-plane axes (u, v) with u x v = normal; for the z=V plane, u = x, v = y."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = helper - normal * (helper @ normal)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def mesh_section(path: Path, plane: str | None, scale: float = 1.0) -> Contour:
    """The outer outline where `plane` cuts the mesh in `path`."""
    import trimesh  # heavy: only when a mesh is asked for

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception:  # trimesh raises many kinds on a bad file, in its own words
        # ("cannot access local variable 'prop_pop'" for a garbage .ply): not a user's to read
        raise ObjectError(f"object file '{path}' could not be read as a "
                          f"{path.suffix.lstrip('.').upper()} mesh: it is damaged or not "
                          "one; export it again from the CAD program") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ObjectError(f"object file '{path}' holds no triangles")
    _check_units(np.asarray(mesh.vertices), scale, path)
    mesh.apply_scale(scale)
    origin, normal = parse_plane(plane, np.asarray(mesh.centroid))
    section = mesh.section(plane_origin=origin, plane_normal=normal)
    if section is None or len(section.entities) == 0:
        along = (np.asarray(mesh.vertices) - origin) @ normal
        lo, hi = (f"{1e3 * v:+.3f}" for v in (along.min(), along.max()))
        misses = along.min() > PLANE_TOUCH or along.max() < -PLANE_TOUCH
        raise ObjectError(f"the plane through {np.round(origin * 1e3, 3).tolist()} mm "
                          f"{'misses' if misses else 'only touches a face of'} the mesh "
                          f"'{path.name}', which lies {lo} to {hi} mm from it along its "
                          "normal: choose a plane through its inside"
                          + ("; the plane is in metres whatever the object's units"
                             if scale != 1.0 else ""))
    if not all(bool(e.closed) for e in section.entities):
        raise ObjectError(f"the section of '{path.name}' is open (the mesh has a hole where "
                          "the plane cuts it): repair the mesh or choose another plane "
                          "(--plane, `scenario.plane`)")
    basis = _plane_basis(normal)
    loops = [Polygon((e.discrete(section.vertices) - origin) @ basis.T)
             for e in section.entities]
    # inner loops are holes the fingers never reach: the union keeps the outer outline
    shape = unary_union([loop.buffer(0) for loop in loops])
    if not isinstance(shape, Polygon):
        raise ObjectError(f"the plane cuts '{path.name}' into {len(shape.geoms)} separate "
                          "pieces; choose a plane through one part (--plane, "
                          "`scenario.plane`)")
    contour = make_contour(np.asarray(shape.exterior.coords)[:-1], path.stem)
    # the centroid and the heading's axis in the mesh's own frame, not the plane's
    centre = origin + basis.T @ np.asarray(contour.origin)
    return dataclasses.replace(contour, origin=tuple(float(v) for v in centre),
                               axis=tuple(float(v) for v in basis[0]),
                               holes=len(loops) - 1)
