"""Scene loading, block cutting, augmentation and batching on small synthetic scenes."""
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from fpcc_ros.training.dataset import (BlockDataset, DataConfig, augment_points, collate,
                                       find_scenes, load_scene, scene_blocks)

A, B = 0.06, 0.025  # ellipsoid semi-axes (long, short): d_max = A


def fake_scene(seed: int, parts: int = 4, plane_step: float = 0.004) -> dict[str, np.ndarray]:
    """Ellipsoids (d_max = A) lying on a plane at z = 1 m, seen from the origin along +z: the upper
    halves of the parts plus the visible plane, with center scores 1 - (|p - c| / d_max)^2."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(parts)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:parts]
    centers_xy = (grid - (side - 1) / 2) * 0.15 + rng.uniform(-0.01, 0.01, size=(parts, 2))
    half = 0.15 * side / 2
    gx, gy = np.meshgrid(np.arange(-half, half, plane_step), np.arange(-half, half, plane_step))
    plane = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], 1)
    hidden = np.zeros(len(plane), bool)
    xyz, inst, score = [], [], []
    for i, cxy in enumerate(centers_xy):
        yaw = rng.uniform(0, np.pi)
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        center = np.array([cxy[0], cxy[1], 1.0 - B])
        u = rng.normal(size=(3000, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        local = u * np.array([A, B, B])
        local = local[local[:, 2] < 0]                      # the half facing the camera
        pts = local @ rot.T + center
        xyz.append(pts)
        inst.append(np.full(len(pts), i + 1))
        score.append(np.clip(1 - (np.linalg.norm(pts - center, axis=1) / A) ** 2, 0, 1))
        pl = (plane - center) @ rot                           # plane in the part's frame
        hidden |= (pl[:, 0] / A) ** 2 + (pl[:, 1] / B) ** 2 < 1
    xyz.append(plane[~hidden])
    inst.append(np.zeros((~hidden).sum()))
    score.append(np.zeros((~hidden).sum()))
    return {"points": np.concatenate(xyz).astype(np.float32),
            "instance": np.concatenate(inst).astype(np.int32),
            "center_score": np.concatenate(score).astype(np.float32),
            "part_radius": np.float32(A), "part_name": np.array("ellipsoid")}


def write_fake_scenes(folder: Path, count: int = 3, organised_first: bool = True) -> list[Path]:
    """Write ``count`` scene NPZ files; the first as an organised (H, W, 3) cloud with NaN holes."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        scene = fake_scene(seed=i)
        if organised_first and i == 0:
            n = len(scene["points"])
            w = 64
            h = -(-n // w) + 1                                  # at least one all-NaN row
            for key, fill in (("points", np.nan), ("instance", 0), ("center_score", 0)):
                arr = scene[key]
                full = np.full((h * w,) + arr.shape[1:], fill, dtype=arr.dtype)
                full[:n] = arr
                scene[key] = full.reshape((h, w) + arr.shape[1:])
        path = folder / f"scene_{i:03d}.npz"
        np.savez(path, **scene)
        paths.append(path)
    return paths


SMALL = DataConfig(k=8, block_size=256, voxel_factor=0.15, remove_floor=False)


def test_fake_scene_center_scores_follow_the_formula():
    s = fake_scene(0)
    part = s["instance"] == 1
    assert part.sum() > 100 and (s["instance"] == 0).sum() > 100
    assert s["center_score"][part].max() > 0.7          # the top of a part is near its center
    assert (s["center_score"][~part & (s["instance"] == 0)] == 0).all()


def test_load_scene_organised_with_nan(tmp_path):
    paths = write_fake_scenes(tmp_path, count=1)
    raw = np.load(paths[0])
    scene = load_scene(paths[0])
    finite = np.isfinite(raw["points"]).all(-1)
    assert raw["points"].ndim == 3 and not finite.all()
    assert len(scene.xyz) == finite.sum() and np.isfinite(scene.xyz).all()
    assert scene.num_pixels == raw["points"].shape[0] * raw["points"].shape[1]
    np.testing.assert_array_equal(scene.instance, raw["instance"][finite])
    assert scene.part_radius == pytest.approx(A) and scene.part_name == "ellipsoid"


def test_load_scene_errors_name_the_field(tmp_path):
    good = fake_scene(0)
    missing = {k: v for k, v in good.items() if k != "center_score"}
    np.savez(tmp_path / "missing.npz", **missing)
    with pytest.raises(ValueError, match="center_score"):
        load_scene(tmp_path / "missing.npz")
    np.savez(tmp_path / "shape.npz", **{**good, "instance": good["instance"][:-1]})
    with pytest.raises(ValueError, match="instance has shape"):
        load_scene(tmp_path / "shape.npz")
    np.savez(tmp_path / "radius.npz", **{**good, "part_radius": np.float32(0)})
    with pytest.raises(ValueError, match="part_radius"):
        load_scene(tmp_path / "radius.npz")


def test_find_scenes(tmp_path):
    paths = write_fake_scenes(tmp_path / "a", count=2)
    assert find_scenes([tmp_path]) == paths
    with pytest.raises(FileNotFoundError, match="does not exist"):
        find_scenes([tmp_path / "nope"])


def test_scene_blocks_cover_every_representative_once():
    scene = load_scene_dict(fake_scene(1))
    cut = scene_blocks(scene, SMALL, skip_empty=False)
    assert len(cut.blocks) > 2
    covered = np.concatenate([b.index for b in cut.blocks])
    np.testing.assert_array_equal(np.sort(covered), np.arange(len(cut.rep)))
    assert cut.inverse is not None and cut.inverse.max() == len(cut.rep) - 1
    for b in cut.blocks:
        n = len(b.xyz)
        assert 0 < n <= SMALL.block_size
        assert b.features.shape == (n, 6) and b.features.dtype == np.float32
        assert b.knn.shape == (n, SMALL.k) and b.knn.dtype == np.int64
        assert b.knn.min() >= 0 and b.knn.max() < n
        np.testing.assert_array_equal(b.knn[:, 0], np.arange(n))          # self first
        assert (b.features[:, 3:] >= 0).all() and (b.features[:, 3:] <= 1 + 1e-6).all()
        rows = cut.rep[b.index]                                             # labels follow the points
        np.testing.assert_array_equal(b.xyz, scene.xyz[rows])
        np.testing.assert_array_equal(b.instance, scene.instance[rows])
        np.testing.assert_array_equal(b.center_score, scene.center_score[rows])


def test_voxel_factor_sets_the_density():
    scene = load_scene_dict(fake_scene(1))
    coarse = scene_blocks(scene, DataConfig(k=8, block_size=256, voxel_factor=0.3, remove_floor=False), skip_empty=False)
    fine = scene_blocks(scene, DataConfig(k=8, block_size=256, voxel_factor=0.1, remove_floor=False), skip_empty=False)
    assert len(fine.rep) > 4 * len(coarse.rep)  # 3x finer voxels on a surface: ~9x the points


def test_blocks_without_parts_are_skipped():
    raw = fake_scene(1)
    far = np.stack(np.meshgrid(np.linspace(5, 6, 40), np.linspace(5, 6, 40), [1.0]), -1).reshape(-1, 3)
    raw = {**raw, "points": np.concatenate([raw["points"], far.astype(np.float32)]),
           "instance": np.concatenate([raw["instance"], np.zeros(len(far), np.int32)]),
           "center_score": np.concatenate([raw["center_score"], np.zeros(len(far), np.float32)])}
    scene = load_scene_dict(raw)
    every = scene_blocks(scene, SMALL, skip_empty=False).blocks
    kept = scene_blocks(scene, SMALL, skip_empty=True).blocks
    assert len(kept) < len(every)
    assert all((b.instance > 0).any() for b in kept)
    assert sum(not (b.instance > 0).any() for b in every) == len(every) - len(kept)


def test_augment_points_rotates_about_z_and_scales():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 1, size=(50, 3)).astype(np.float32)
    out = augment_points(xyz, DataConfig(), np.random.default_rng(3))
    d_in = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    d_out = np.linalg.norm(out[:, None] - out[None], axis=-1)
    ratio = d_out[d_in > 0] / d_in[d_in > 0]
    assert np.ptp(ratio) < 1e-4 and 0.9 <= ratio[0] <= 1.1                 # one uniform scale
    np.testing.assert_allclose(out[:, 2] - out[:, 2].mean(), ratio[0] * (xyz[:, 2] - xyz[:, 2].mean()),
                               atol=1e-5)                                   # depth only scaled
    assert not np.allclose(out[:, :2], xyz[:, :2], atol=1e-3)               # x, y rotated


def test_augmented_epochs_are_seeded(tmp_path):
    paths = write_fake_scenes(tmp_path, count=2)
    ds = BlockDataset(paths, SMALL, augment=True, seed=7)
    again = BlockDataset(paths, SMALL, augment=True, seed=7)
    e0, e0b, e1 = ds.epoch_blocks(0), again.epoch_blocks(0), ds.epoch_blocks(1)
    assert len(e0) == len(e0b) and all(np.array_equal(a.xyz, b.xyz) for a, b in zip(e0, e0b))
    assert not all(len(a.xyz) == len(b.xyz) and np.array_equal(a.xyz, b.xyz) for a, b in zip(e0, e1))
    for b in e0 + e1:
        assert len(b.xyz) <= SMALL.block_size and (b.instance > 0).any()
        assert b.knn.max() < len(b.xyz)


def test_augmented_dataset_downsamples_each_scene_as_it_reads_it(tmp_path, monkeypatch):
    """Never all full-resolution scenes in memory at once: a big training set (1,764 scenes)
    would otherwise need ~18 GB before the first downsampling."""
    import fpcc_ros.training.dataset as dataset
    paths = write_fake_scenes(tmp_path, count=3)
    full_alive, most = [], [0]
    real_load, real_down = dataset.load_scene, dataset._predownsample

    def load(path):
        scene = real_load(path)
        full_alive.append(len(scene.xyz))
        most[0] = max(most[0], len(full_alive))
        return scene

    def down(scene, factor):
        full_alive.pop()
        return real_down(scene, factor)

    monkeypatch.setattr(dataset, "load_scene", load)
    monkeypatch.setattr(dataset, "_predownsample", down)
    ds = BlockDataset(paths, SMALL, augment=True, seed=7)
    assert most[0] == 1 and not full_alive
    assert all(len(s.xyz) < len(real_load(p).xyz) for s, p in zip(ds.scenes, paths))


def test_fixed_dataset_batches_cover_all_blocks(tmp_path):
    ds = BlockDataset(write_fake_scenes(tmp_path, count=2), SMALL, augment=False)
    blocks = ds.epoch_blocks(0)
    groups = ds.batches(0, 3)
    assert sorted(id(b) for g in groups for b in g) == sorted(id(b) for b in blocks)
    assert all(1 <= len(g) <= 3 for g in groups)
    assert [[id(b) for b in g] for g in groups] == [[id(b) for b in g] for g in ds.batches(0, 3)]
    batch = next(ds.iter_batches(0, 3))
    assert set(batch) == {"features", "knn", "xyz", "instance", "center_score", "valid", "part_radius"}


def test_collate_pads_by_repeating_points():
    scene = load_scene_dict(fake_scene(2))
    blocks = scene_blocks(scene, DataConfig(k=8, block_size=100, voxel_factor=0.15, remove_floor=False)).blocks
    small, big = sorted(blocks, key=lambda b: len(b.xyz))[0], sorted(blocks, key=lambda b: len(b.xyz))[-1]
    assert len(small.xyz) < len(big.xyz)
    batch = collate([big, small])
    m, n = len(big.xyz), len(small.xyz)
    assert batch["features"].shape == (2, m, 6) and batch["knn"].shape == (2, m, 8)
    assert batch["knn"].dtype == torch.int64 and batch["features"].dtype == torch.float32
    assert batch["valid"][0].all() and batch["valid"][1].sum() == n and batch["valid"][1, :n].all()
    np.testing.assert_array_equal(batch["xyz"][1, n:].numpy(), small.xyz[np.arange(m - n) % n])
    assert batch["knn"][1].max() < n                       # padded rows point at real points
    assert batch["part_radius"].tolist() == pytest.approx([A, A])


def load_scene_dict(raw: dict):
    """load_scene on an in-memory dict (through a temporary NPZ file)."""
    with tempfile.NamedTemporaryFile(suffix=".npz") as fh:
        np.savez(fh, **raw)
        fh.flush()
        return load_scene(fh.name)
