"""Synthetic scenes: determinism, labels, center scores, camera geometry, dataset writing, CLI.

Tiny scenes (3 parts, 160 x 120 pixels) keep every test well under a second of physics.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fpcc_ros.training.mesh import load_mesh, prepare_collision
from fpcc_ros.training.parts import make_part
from fpcc_ros.training.synth import generate_dataset, generate_scene

SHARED = Path(__file__).resolve().parents[2] / "shared"
MESHES = SHARED / "data" / "meshes"
W, H = 160, 120
KEYS = ("points", "instance", "center_score", "part_radius", "camera_K", "part_name", "seed",
        "num_parts", "visible_points", "centers")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("collision"))


@pytest.fixture(scope="module")
def part():
    return make_part("gear_shaft", 0)


@pytest.fixture(scope="module")
def clean(part, cache):
    """A noise-free scene (ideal depth) and the same scene with sensor effects."""
    ideal = generate_scene(part, 3, seed=11, width=W, height=H, noise=False, cache_dir=cache)
    noisy = generate_scene(part, 3, seed=11, width=W, height=H, noise=True, cache_dir=cache)
    return ideal, noisy


def _same(a: dict, b: dict) -> bool:
    def equal(x, y) -> bool:
        x, y = np.asarray(x), np.asarray(y)
        return np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)


def test_keys_shapes_dtypes(clean):
    scene = clean[1]
    for key in KEYS:
        assert key in scene
    k = int(scene["num_parts"])
    assert 1 <= k <= 3
    assert scene["points"].shape == (H, W, 3) and scene["points"].dtype == np.float32
    assert scene["instance"].shape == (H, W) and scene["instance"].dtype == np.int32
    assert scene["center_score"].shape == (H, W) and scene["center_score"].dtype == np.float32
    assert scene["centers"].shape == (k, 3)
    assert scene["visible_points"].shape == (k + 1,) and scene["visible_points"].dtype == np.int32
    assert np.asarray(scene["part_radius"]).shape == ()


def test_same_seed_identical_different_seed_differs(part, cache):
    a = generate_scene(part, 3, seed=5, width=W, height=H, cache_dir=cache)
    generate_scene(part, 3, seed=6, width=W, height=H, cache_dir=cache)  # nothing carries over
    b = generate_scene(part, 3, seed=5, width=W, height=H, cache_dir=cache)
    assert _same(a, b)
    c = generate_scene(part, 3, seed=7, width=W, height=H, cache_dir=cache)
    assert not np.array_equal(a["points"], c["points"], equal_nan=True)


def test_labels_and_visible_points(clean):
    for scene in clean:
        inst, k = scene["instance"], int(scene["num_parts"])
        assert inst.min() >= 0 and inst.max() <= k
        counts = np.array([(inst == i).sum() for i in range(1, k + 1)])
        np.testing.assert_array_equal(scene["visible_points"][1:], counts)
        assert scene["visible_points"][0] == 0
        # no point, no label
        assert np.all(inst[~np.isfinite(scene["points"][..., 2])] == 0)
        assert counts.sum() > 0


def test_center_score_range_background_and_formula(clean, part):
    ideal = clean[0]
    for scene in clean:
        s = scene["center_score"]
        assert s.min() >= 0.0 and s.max() <= 1.0
        assert np.all(s[scene["instance"] == 0] == 0.0)
    # noise-free points: the score is the paper's formula from the stored centers
    inst = ideal["instance"]
    m = inst > 0
    c = ideal["centers"][inst[m] - 1].astype(np.float64)
    d = np.linalg.norm(ideal["points"][m].astype(np.float64) - c, axis=1)
    expected = np.clip(1.0 - (d / float(ideal["part_radius"])) ** 2, 0.0, 1.0)
    np.testing.assert_allclose(ideal["center_score"][m], expected, atol=1e-4)
    assert float(ideal["part_radius"]) == pytest.approx(part.d_max)


def test_points_lie_on_the_posed_meshes(clean, part):
    """Noise-free points of each instance lie on that part's mesh placed at its stored pose."""
    ideal = clean[0]
    inst = ideal["instance"]
    samples, _ = trimesh.sample.sample_surface(part.to_trimesh(), 40000, seed=0)
    for i in range(1, int(ideal["num_parts"]) + 1):
        pts = ideal["points"][inst == i].astype(np.float64)
        if len(pts) == 0:
            continue
        T = ideal["part_poses"][i - 1].astype(np.float64)
        surf = samples @ T[:3, :3].T + T[:3, 3]
        dist, _ = cKDTree(surf).query(pts)
        assert np.percentile(dist, 95) < 0.003, f"instance {i}: {np.percentile(dist, 95):.4f} m off its mesh"
        # every surface point is within d_max of the geometric center
        assert np.linalg.norm(pts - ideal["centers"][i - 1], axis=1).max() <= part.d_max + 0.002


def test_optical_frame_and_floor(clean):
    ideal = clean[0]
    pts = ideal["points"].reshape(-1, 3).astype(np.float64)
    ok = np.isfinite(pts[:, 2])
    assert ok.mean() > 0.9  # noise off: everything but the far floor returns
    assert np.all(pts[ok, 2] > 0)  # z forward
    T = ideal["camera_pose"]
    assert T[2, 2] < -np.cos(np.radians(20))  # optical axis looks down, tilt <= 20 degrees
    world = pts[ok] @ T[:3, :3].T + T[:3, 3]
    # outside the largest possible tote (0.72 x 0.48 inner + walls) only the floor (z = 0) is seen
    outside = (np.abs(world[:, 0]) > 0.42) | (np.abs(world[:, 1]) > 0.3)
    assert outside.sum() > 100
    np.testing.assert_allclose(world[outside, 2], 0.0, atol=2e-4)
    # image x grows to the right: a point right of the principal point has x > 0
    K = ideal["camera_K"]
    assert K[0, 0] == pytest.approx(K[1, 1], rel=0.01) and 550 * W / 640 <= K[0, 0] <= 650 * W / 640
    col = ideal["points"][:, :, 0]
    right = np.arange(W) > K[0, 2] + 1
    assert np.all(col[:, right][np.isfinite(col[:, right])] > 0)


def test_sensor_effects(clean):
    ideal, noisy = clean
    z0, z1 = ideal["points"][..., 2], noisy["points"][..., 2]
    # same physics and camera: labels agree wherever the noisy scene keeps one
    m = noisy["instance"] > 0
    np.testing.assert_array_equal(noisy["instance"][m], ideal["instance"][m])
    np.testing.assert_array_equal(noisy["centers"], ideal["centers"])
    assert np.isnan(z1).sum() > np.isnan(z0).sum()  # dropouts
    diff = np.abs(z1 - z0)[m]
    assert 0 < np.median(diff) < 0.005  # millimetre range noise on labelled points
    # flying pixels: part pixels that keep a depth but lose their label, off every surface
    flying = (ideal["instance"] > 0) & (noisy["instance"] == 0) & np.isfinite(z1)
    assert flying.sum() > 0
    assert np.all(noisy["center_score"][flying] == 0)


def test_dataset_files_seeds_and_workers(part, cache, tmp_path):
    kw = dict(parts_range=(2, 3), width=W, height=H, cache_dir=cache, progress=False)
    one = generate_dataset(tmp_path / "w1", part, 2, seed=40, workers=1, **kw)
    two = generate_dataset(tmp_path / "w2", part, 2, seed=40, workers=2, **kw)
    assert [p.name for p in one] == ["scene_00000.npz", "scene_00001.npz"]
    assert (tmp_path / "w1" / "synth.json").exists()
    for a, b in zip(one, two):
        with np.load(a) as fa, np.load(b) as fb:
            assert _same(dict(fa), dict(fb))
    direct = generate_scene(part, seed=41, parts_range=(2, 3), width=W, height=H, cache_dir=cache)
    with np.load(one[1], allow_pickle=False) as f:
        assert _same(dict(f), direct)
        assert str(f["part_name"]) == "gear_shaft"


def _synth_cli(argv: list[str]) -> int:
    from fpcc_ros.commands import synth
    parser = argparse.ArgumentParser()
    synth.add_arguments(parser)
    return synth.run(parser.parse_args(argv))


def test_synth_cli(tmp_path, capsys):
    out = tmp_path / "scenes"
    rc = _synth_cli(["--part", "hex_nut", "--out", str(out), "--scenes", "1", "--workers", "1",
                     "--parts", "2", "3", "--width", str(W), "--height", str(H)])
    assert rc == 0 and (out / "scene_00000.npz").exists()
    capsys.readouterr()
    assert _synth_cli(["--part", "nope", "--out", str(out)]) != 0
    err = capsys.readouterr().err
    assert "hex_nut" in err and len(err.strip().splitlines()) == 1
    assert _synth_cli(["--mesh", str(tmp_path / "missing.stl"), "--out", str(out)]) != 0
    assert "missing.stl" in capsys.readouterr().err
    assert _synth_cli(["--part", "ring", "--out", str(out), "--parts", "5", "2"]) != 0


@pytest.mark.shared
@pytest.mark.skipif(not MESHES.exists(), reason="../shared meshes absent")
def test_shared_gear_shaft_scene(tmp_path):
    gear = load_mesh(MESHES / "IPAGearShaft.stl", scale=0.5)
    assets = prepare_collision(gear, tmp_path)
    scene = generate_scene(gear, 3, seed=2, width=W, height=H, assets=assets)
    assert float(scene["part_radius"]) == pytest.approx(gear.d_max)
    assert int(scene["num_parts"]) == 3 and (scene["visible_points"][1:] > 0).sum() >= 2


def test_dense_range_fills_the_bin_where_the_default_stops_at_60():
    """A full bin is 2.5 layers of parts lying flat on the 0.6 x 0.4 m floor (capped at 100
    copies); the default range stops at 60, short of that for long thin parts."""
    from fpcc_ros.training.parts import BUILTIN_PARTS
    from fpcc_ros.training.synth import default_parts_range, dense_parts_range

    def layers(part, copies: int) -> float:  # flat area of `copies` parts over the floor area
        e = np.sort(part.extents)[::-1]
        s = float(np.clip(part.d_max / 0.06, 0.5, 1.0))
        return copies * 0.7 * e[0] * e[1] / (0.6 * s * 0.4 * s)

    shaft = make_part("gear_shaft", 38)
    assert default_parts_range(shaft)[1] == 60 and layers(shaft, 60) < 2.0
    lo, hi = dense_parts_range(shaft)
    assert 60 < hi <= 100 and layers(shaft, hi) == pytest.approx(2.5, abs=0.05)
    assert layers(shaft, lo) == pytest.approx(1.0, abs=0.05)
    for name in BUILTIN_PARTS:
        part = make_part(name, 38)
        (dlo, dhi), (lo, hi) = default_parts_range(part), dense_parts_range(part)
        assert lo >= dlo and hi >= dhi and hi - lo >= 5 and hi <= 100, name
        assert hi == 100 or layers(part, hi) == pytest.approx(2.5, abs=0.05), name
