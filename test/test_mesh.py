"""Part meshes: geometric center and d_max against hand-computed values, loading and errors."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fpcc_ros.training.mesh import MeshError, load_mesh, part_from_trimesh, prepare_collision

SHARED = Path(__file__).resolve().parents[2] / "shared"
MESHES = SHARED / "data" / "meshes"
needs_shared = pytest.mark.skipif(not MESHES.exists(), reason="../shared meshes absent")


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    move = trimesh.transformations.translation_matrix((lo + hi) / 2)
    return trimesh.creation.box(extents=hi - lo, transform=move)


def _reference_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Volume centroid of a closed mesh by signed tetrahedra from the origin (divergence theorem)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()


def test_cube_center_and_dmax():
    part = part_from_trimesh(_box([0.15, 0.25, 0.35], [0.25, 0.35, 0.45]), "cube")
    np.testing.assert_allclose(part.center, [0.2, 0.3, 0.4], atol=1e-12)
    assert part.d_max == pytest.approx(np.sqrt(3) * 0.05, rel=1e-12)
    assert part.center_kind == "volume"
    assert part.volume == pytest.approx(1e-3, rel=1e-9)


def test_cylinder_center_and_dmax():
    cyl = trimesh.creation.cylinder(radius=0.05, height=0.2, sections=64)
    cyl.apply_translation([0.0, 0.0, 0.1])  # base on z = 0
    part = part_from_trimesh(cyl, "cyl")
    np.testing.assert_allclose(part.center, [0, 0, 0.1], atol=1e-9)
    assert part.d_max == pytest.approx(np.hypot(0.05, 0.1), rel=1e-9)


def test_l_shape_center_is_volume_centroid_not_bbox_center():
    # A: 0.2 x 0.1 x 0.1 (volume 2e-3, centroid (0.1, 0.05, 0.05)); B on top of A's left half:
    # 0.1 x 0.1 x 0.1 (volume 1e-3, centroid (0.05, 0.05, 0.15)) -> (0.25/3, 0.05, 0.25/3)
    mesh = trimesh.util.concatenate([_box([0, 0, 0], [0.2, 0.1, 0.1]), _box([0, 0, 0.1], [0.1, 0.1, 0.2])])
    part = part_from_trimesh(mesh, "L")
    np.testing.assert_allclose(part.center, [0.25 / 3, 0.05, 0.25 / 3], atol=1e-9)
    # farthest vertex from the centroid: the corner (0.2, 0 or 0.1, 0) or (0, *, 0.2)
    expected = np.linalg.norm(np.array([0.2, 0.1, 0.0]) - [0.25 / 3, 0.05, 0.25 / 3])
    assert part.d_max == pytest.approx(expected, rel=1e-9)


def test_open_mesh_uses_surface_centroid():
    cube = _box([0, 0, 0], [0.1, 0.1, 0.1])
    top = np.all(np.isclose(cube.triangles[:, :, 2], 0.1), axis=1)
    open_box = trimesh.Trimesh(cube.vertices, cube.faces[~top], process=False)
    part = part_from_trimesh(open_box, "open")
    # five unit faces: bottom at z=0, four sides centered at z=0.05 -> z = 0.2 / 5
    assert part.center_kind == "surface"
    np.testing.assert_allclose(part.center, [0.05, 0.05, 0.04], atol=1e-12)


def test_load_units_and_scale(tmp_path):
    path = tmp_path / "cube_mm.stl"
    _box([0, 0, 0], [100, 50, 20]).export(path)
    part = load_mesh(path, unit="mm")
    np.testing.assert_allclose(part.extents, [0.1, 0.05, 0.02], atol=1e-9)
    half = load_mesh(path, unit="mm", scale=0.5)
    np.testing.assert_allclose(half.extents, [0.05, 0.025, 0.01], atol=1e-9)
    assert half.d_max == pytest.approx(0.5 * np.linalg.norm([0.05, 0.025, 0.01]), rel=1e-9)
    inches = load_mesh(path, unit="cm", scale=0.1)  # 100 cm * 0.1 = 0.1 m
    np.testing.assert_allclose(inches.extents, [0.1, 0.05, 0.02], atol=1e-9)


def test_obj_with_split_vertices_is_still_a_volume(tmp_path):
    path = tmp_path / "cube.obj"
    cube = _box([0, 0, 0], [0.1, 0.1, 0.1])
    cube.export(path, include_normals=True)
    part = load_mesh(path)
    assert part.center_kind == "volume"
    np.testing.assert_allclose(part.center, [0.05, 0.05, 0.05], atol=1e-9)


def test_missing_file_names_the_path(tmp_path):
    missing = tmp_path / "nope.stl"
    with pytest.raises(MeshError, match="nope.stl"):
        load_mesh(missing)


def test_wrong_units_and_flat_and_empty_meshes(tmp_path):
    big = tmp_path / "big.stl"
    _box([0, 0, 0], [100, 50, 20]).export(big)  # millimetres read as metres
    with pytest.raises(MeshError, match="check units"):
        load_mesh(big)
    tiny = tmp_path / "tiny.stl"
    _box([0, 0, 0], [0.1, 0.05, 0.02]).export(tiny)  # metres read as millimetres
    with pytest.raises(MeshError, match="has no volume"):
        load_mesh(tiny, unit="mm")
    flat = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(MeshError, match="has no volume"):
        part_from_trimesh(flat, "flat")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(MeshError, match="empty"):
        load_mesh(empty)
    with pytest.raises(MeshError, match="unit"):
        load_mesh(big, unit="furlong")


def _obj_pieces(path: str) -> list[np.ndarray]:
    """Vertices of each 'o' object of an OBJ file."""
    pieces: list[list] = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("o "):
            pieces.append([])
        elif line.startswith("v "):
            pieces[-1].append([float(x) for x in line.split()[1:4]])
    return [np.array(p) for p in pieces]


def test_collision_hull_for_compact_pieces_for_ring(tmp_path):
    from scipy.spatial import ConvexHull
    cube = part_from_trimesh(_box([0, 0, 0], [0.1, 0.1, 0.1]), "cube")
    assets = prepare_collision(cube, tmp_path)
    assert assets.kind == "hull" and Path(assets.collision_obj).exists()
    ring_mesh = trimesh.creation.annulus(r_min=0.04, r_max=0.05, height=0.02)
    ring = part_from_trimesh(ring_mesh, "ring")
    a1 = prepare_collision(ring, tmp_path)
    assert a1.kind == "decompose"
    pieces = _obj_pieces(a1.collision_obj)
    assert 4 <= len(pieces) <= 32
    hulls = [ConvexHull(p) for p in pieces]
    # together about the ring's volume (one hull over the hole would be 2.8x) ...
    total = sum(h.volume for h in hulls)
    assert 0.9 * ring.volume < total < 1.3 * ring.volume
    # ... and no piece covers the hole: points within 0.035 m of the axis are outside all hulls
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    probe = np.concatenate([np.column_stack([r * np.cos(a), r * np.sin(a), np.full(64, z)])
                            for r in (0.0, 0.02, 0.035) for z in (-0.005, 0.0, 0.005)])
    for h in hulls:
        inside = np.all(probe @ h.equations[:, :3].T + h.equations[:, 3] <= 0, axis=1)
        assert not inside.any()
    # pybullet reads the file as a compound with one convex child per piece
    import pybullet as p
    client = p.connect(p.DIRECT)
    try:
        shape = p.createCollisionShape(p.GEOM_MESH, fileName=a1.collision_obj, physicsClientId=client)
        body = p.createMultiBody(1.0, shape, physicsClientId=client)
        assert len(p.getCollisionShapeData(body, -1, physicsClientId=client)) == len(pieces)
    finally:
        p.disconnect(client)
    assert prepare_collision(ring, tmp_path) == a1  # cached


@pytest.mark.shared
@needs_shared
def test_shared_meshes_dmax():
    gear = load_mesh(MESHES / "IPAGearShaft.stl", scale=0.5)
    raw = trimesh.load(MESHES / "IPAGearShaft.stl", force="mesh")
    v = np.asarray(raw.vertices) * 0.5
    c = _reference_centroid(v, np.asarray(raw.faces))
    np.testing.assert_allclose(gear.center, c, atol=1e-7)
    assert gear.d_max == pytest.approx(np.linalg.norm(v - c, axis=1).max(), rel=1e-9)
    assert 0.109 < gear.d_max < 0.13  # 0.218 m long, centroid 11.6 mm off the middle
    ring = load_mesh(MESHES / "IPARingScrew.stl")
    raw = trimesh.load(MESHES / "IPARingScrew.stl", force="mesh")
    c = _reference_centroid(np.asarray(raw.vertices), np.asarray(raw.faces))
    assert ring.d_max == pytest.approx(np.linalg.norm(raw.vertices - c, axis=1).max(), rel=1e-9)
    assert 0.077 < ring.d_max < 0.09  # 0.154 m long
    tote = load_mesh(MESHES / "tote_box.obj", unit="mm")
    np.testing.assert_allclose(np.sort(tote.extents), [0.212, 0.4, 0.6], atol=1e-6)


def _part_info(argv: list[str]):
    from fpcc_ros.commands import part_info
    parser = argparse.ArgumentParser()
    part_info.add_arguments(parser)
    return part_info.run(parser.parse_args(argv))


def test_part_info_cli(tmp_path, capsys):
    path = tmp_path / "cube_mm.stl"
    _box([0, 0, 0], [100, 100, 100]).export(path)
    assert _part_info([str(path), "--unit", "mm"]) == 0
    out = capsys.readouterr().out
    assert f"{np.sqrt(3) * 0.05:.4f}" in out and "part_radius:=0.0866" in out
    assert _part_info([str(tmp_path / "missing.stl")]) != 0
    err = capsys.readouterr().err
    assert "missing.stl" in err and len(err.strip().splitlines()) == 1
    assert _part_info(["--builtin", "no_such_part"]) != 0
    assert "gear_shaft" in capsys.readouterr().err
    assert _part_info(["--builtin", "washer"]) == 0
    assert "d_max" in capsys.readouterr().out
