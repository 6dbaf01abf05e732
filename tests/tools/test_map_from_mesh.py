"""`haptic map from-mesh`: a meshed part becomes a height map that `haptic run` localizes on."""

import numpy as np
import pytest
import trimesh

from tools.cli import main

PLATE = 0.04
BOSS = (0.05, 0.15, 0.03, 0.015, 0.02)
"""x, y, length, width, height of a block on the plate (metres)."""


def part(domes: int = 24) -> trimesh.Trimesh:
    """A 200 mm block with a smaller block and seeded domes on top, from trimesh primitives.

    The domes are spheres sunk into the block by 20-80 % of their radius; none pokes
    through its underside, which rests on the table.
    """
    plate = trimesh.creation.box(extents=(0.2, 0.2, PLATE))
    plate.apply_translation((0.1, 0.1, PLATE / 2))
    x, y, length, width, height = BOSS
    boss = trimesh.creation.box(extents=(length, width, height))
    boss.apply_translation((x, y, PLATE + height / 2))
    parts = [plate, boss]
    rng = np.random.default_rng(0)
    for _ in range(domes):
        radius = rng.uniform(0.01, 0.022)
        dome = trimesh.creation.icosphere(subdivisions=2, radius=radius)
        dome.apply_translation((*rng.uniform(0.02, 0.18, size=2),
                                PLATE - rng.uniform(0.2, 0.8) * radius))
        parts.append(dome)
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="module")
def part_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mesh")
    mesh = part()
    mesh.export(folder / "part.stl")
    turned = mesh.copy()  # drawn y-up in millimetres, as many CAD exports are
    turned.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    turned.apply_scale(1000)
    turned.export(folder / "part_yup_mm.obj")
    return folder


def test_a_mesh_becomes_a_map_that_run_localizes_on(part_files, capsys):
    out = part_files / "part.npy"
    assert main(["map", "from-mesh", str(part_files / "part.stl"), "--spacing", "0.001",
                 "-o", str(out)]) == 0
    assert "haptic run --map" in capsys.readouterr().out
    heights = np.load(out)
    assert heights.shape == (205, 205)  # 200 mm and two samples of table each side
    x, y, *_, h = BOSS  # map (0, 0) is the mesh's (-2 mm, -2 mm)
    assert heights[round(y * 1000) + 2, round(x * 1000) + 2] == pytest.approx(PLATE + h,
                                                                              abs=1e-6)
    assert heights[0, 0] == 0 and heights[-1, -1] == 0  # the table round the part
    assert main(["run", "--quiet", "--map", str(out), "--spacing", "0.001", "--noise",
                 "--seed", "1"]) == 0
    assert "localized in" in capsys.readouterr().out


def test_up_axis_and_scale_give_the_same_map(part_files):
    a, b = part_files / "a.npy", part_files / "b.npy"
    assert main(["map", "from-mesh", str(part_files / "part.stl"), "--spacing", "0.002",
                 "-o", str(a)]) == 0
    assert main(["map", "from-mesh", str(part_files / "part_yup_mm.obj"), "--spacing", "0.002",
                 "--up", "y", "--scale", "0.001", "-o", str(b)]) == 0
    np.testing.assert_allclose(np.load(a), np.load(b), atol=1e-6)


@pytest.mark.parametrize("mesh, extra, message", [
    ("missing.stl", [], "does not exist"),
    ("broken.stl", [], "no triangles"),
    ("part.stl", ["--region", "1,1,2,2"], "misses the part"),
    ("part.stl", ["--region", "0.1,0,0.05,0.1"], "is empty"),
    ("part.stl", ["--region", "0,0"], "XMIN,YMIN,XMAX,YMAX"),
    ("part.stl", ["--spacing", "0.00001"], "coarser --spacing"),
    ("part_yup_mm.obj", ["--spacing", "0.01"], "--scale 0.001"),  # drawn in millimetres
])
def test_bad_meshes_and_regions_are_one_line_errors(part_files, capsys, mesh, extra, message):
    (part_files / "broken.stl").write_text("solid x\nfacet normal 0 0 banana\n")
    args = ["map", "from-mesh", str(part_files / mesh), "--spacing", "0.001",
            "-o", str(part_files / "x.npy"), *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def round_boss_block() -> trimesh.Trimesh:
    """A block with a round boss and six domes, and flat top between them (found by
    building this test: the default localizer declared wrong poses on it)."""
    plate = trimesh.creation.box(extents=(0.2, 0.2, PLATE))
    plate.apply_translation((0.1, 0.1, PLATE / 2))
    boss = trimesh.creation.cylinder(radius=0.012, height=0.03)
    boss.apply_translation((0.05, 0.15, PLATE + 0.015))
    parts = [plate, boss]
    for x, y, radius, sunk in [(0.15, 0.15, 0.025, 0.5), (0.14, 0.05, 0.02, 0.3),
                               (0.06, 0.06, 0.018, 0.6), (0.10, 0.10, 0.03, 0.3),
                               (0.17, 0.10, 0.015, 0.2), (0.09, 0.17, 0.016, 0.4)]:
        dome = trimesh.creation.icosphere(subdivisions=3, radius=radius)
        dome.apply_translation((x, y, PLATE - sunk * radius))
        parts.append(dome)
    return trimesh.util.concatenate(parts)


@pytest.mark.parametrize("seed", [1, 2])
def test_no_wrong_declaration_after_a_plain_and_a_round_boss(tmp_path, seed):
    """After five readings on the flat top and two climbing the round boss, many poses
    round the boss fit exactly; the truth had left the pool and one of them was declared,
    until a sweep over the whole map had to pass first (issue 9 item 3)."""
    from service.episode.scenario import RunSettings
    from service.episode.simulate import simulate
    from service.localization.mesh_map import mesh_height_map

    round_boss_block().export(tmp_path / "block.stl")
    height_map = mesh_height_map(tmp_path / "block.stl", 0.001).height_map
    np.save(tmp_path / "block.npy", height_map.heights)
    settings = RunSettings(map=str(tmp_path / "block.npy"), spacing=0.001, seed=seed)
    assert not simulate(settings, height_map).score.wrong_declaration
