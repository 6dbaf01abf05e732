"""A height map of a meshed object seen from above: one vertical ray per sample (trimesh).

The part rests on a table at its lowest point: a ray that misses the part reads the
table (height 0), and heights are metres above it. The mesh is first turned so that its
`up` axis points up (the turns are fixed, see `UP_TURNS`), and scaled (`scale=0.001` for
a mesh drawn in millimetres). The map's sample [row, col] lies at (x, y) = (x0 + col *
spacing, y0 + row * spacing) of the turned mesh, so rows run along y.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.errors import MapError
from service.localization.maps import MAX_SAMPLES
from service.localization.surface import HeightMap

UP_TURNS: dict[str, tuple[tuple[int, int, int], ...]] = {
    "z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),     # as drawn
    "-z": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # half turn about x
    "y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),    # quarter turn about x: map y = -mesh z
    "-y": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),   # map y = mesh z
    "x": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),    # quarter turn about y: map x = -mesh z
    "-x": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),   # map x = mesh z
}
"""Rows of the rotation that takes the mesh's `up` axis to the map's up (+z)."""
LARGEST_PART = 2.0
"""Metres. A part wider than this is more likely a mesh drawn in millimetres."""
MARGIN_SAMPLES = 2
"""By default the map covers the part's footprint and this many samples of table round it."""


@dataclass(frozen=True)
class MeshMap:
    height_map: HeightMap
    origin: tuple[float, float]
    """(x, y) of sample [0, 0] in the turned, scaled mesh's frame (metres)."""
    faces: int
    hit_share: float
    """Share of the samples whose ray hit the part (the rest read the table)."""
    warnings: tuple[str, ...] = ()


def load_mesh(path: Path, up: str = "z", scale: float = 1.0):
    """The mesh in `path`, turned so `up` points up and scaled to metres."""
    import trimesh

    if up not in UP_TURNS:
        raise MapError(f"--up must be one of {', '.join(UP_TURNS)}, got '{up}'")
    if not (np.isfinite(scale) and scale > 0):
        raise MapError(f"--scale must be a positive number, got {scale}")
    if not path.is_file():
        raise MapError(f"mesh file '{path}' does not exist")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # a user's file: any parser failure is a bad input
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MapError(f"mesh file '{path}' could not be read as a mesh: {first}") from None
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise MapError(f"mesh file '{path}' has no triangles (an empty or unsupported mesh)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MapError(f"mesh file '{path}' has non-finite vertex coordinates")
    turn = np.eye(4)
    turn[:3, :3] = np.array(UP_TURNS[up], dtype=float) * scale
    mesh.apply_transform(turn)
    return mesh


def parse_region(text: str | None) -> tuple[float, float, float, float] | None:
    """'XMIN,YMIN,XMAX,YMAX' (metres) to a tuple, or None."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(np.isfinite(values)):
        raise MapError(f"--region takes XMIN,YMIN,XMAX,YMAX in metres, got '{text}'")
    return values  # type: ignore[return-value]


def mesh_height_map(path: Path, spacing: float, up: str = "z", scale: float = 1.0,
                    region: tuple[float, float, float, float] | None = None) -> MeshMap:
    """The height map of the mesh in `path` seen from above, `spacing` metres apart."""
    if not (np.isfinite(spacing) and spacing > 0):
        raise MapError(f"--spacing must be a positive number of metres, got {spacing}")
    mesh = load_mesh(path, up, scale)
    (mx0, my0, floor), (mx1, my1, top) = mesh.bounds
    if region is None:
        margin = MARGIN_SAMPLES * spacing
        region = (mx0 - margin, my0 - margin, mx1 + margin, my1 + margin)
    x0, y0, x1, y1 = region
    footprint = (f"the mesh spans x {mx0:.4g}..{mx1:.4g} m, y {my0:.4g}..{my1:.4g} m "
                 f"(after --up {up}, --scale {scale:g})")
    warnings = []
    if max(mx1 - mx0, my1 - my0, top - floor) > LARGEST_PART:
        warnings.append(f"the part is {max(mx1 - mx0, my1 - my0, top - floor):.4g} m across: "
                        "if the mesh is in millimetres, give --scale 0.001")
        footprint += f"; {warnings[-1]}"
    if x1 <= x0 or y1 <= y0:
        raise MapError(f"--region {x0:g},{y0:g},{x1:g},{y1:g} is empty (XMAX must exceed "
                       f"XMIN and YMAX exceed YMIN); {footprint}")
    cols, rows = int((x1 - x0) / spacing + 1e-9) + 1, int((y1 - y0) / spacing + 1e-9) + 1
    if max(cols, rows) < 2:
        raise MapError(f"the region is under two samples wide at --spacing {spacing:g} m; "
                       f"{footprint}")
    if cols * rows > MAX_SAMPLES:
        raise MapError(f"the map would be {cols} x {rows} samples (at most {MAX_SAMPLES:,}); "
                       f"choose a coarser --spacing or a smaller --region; {footprint}")
    xs, ys = x0 + np.arange(cols) * spacing, y0 + np.arange(rows) * spacing
    gx, gy = np.meshgrid(xs, ys)
    origins = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, top + 1.0)])
    directions = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    heights = np.zeros(gx.size)
    hits, ray_index, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    if len(ray_index) == 0:
        raise MapError(f"--region {x0:g},{y0:g},{x1:g},{y1:g} misses the part; {footprint}")
    heights[ray_index] = hits[:, 2] - floor
    hit = np.zeros(gx.size, dtype=bool)
    hit[ray_index] = True
    height_map = HeightMap(heights.reshape(rows, cols), spacing, name=path.stem)
    return MeshMap(height_map, (float(x0), float(y0)), len(mesh.faces), float(hit.mean()),
                   tuple(warnings))


def check_output(out: Path) -> None:
    """Refuse an output `load_map` could not read back, or a folder that does not exist."""
    if out.suffix.lower() not in {".npy", ".csv", ".txt"}:
        raise MapError(f"-o {out}: write a .npy, .csv or .txt file")
    if not out.resolve().parent.is_dir():
        raise MapError(f"cannot write {out}: folder {out.parent} does not exist")


def save_heights(height_map: HeightMap, out: Path) -> None:
    """Write the heights where `load_map` reads them: .npy, or .csv / .txt text."""
    check_output(out)
    suffix = out.suffix.lower()
    if suffix == ".npy":
        np.save(out, height_map.heights)
    else:
        np.savetxt(out, height_map.heights, delimiter="," if suffix == ".csv" else " ")
