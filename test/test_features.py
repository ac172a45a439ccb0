"""Network-input helpers shared by runtime and training, on cases checked by hand."""
import numpy as np
import pytest

from fpcc_ros.features import (block_features, dominant_plane, knn_graph, plane_tolerance,
                               spatial_blocks, tile_order, voxel_downsample)


def test_voxel_downsample_keeps_one_real_point_per_voxel_and_maps_back():
    xyz = np.array([[0.01, 0.01, 0], [0.02, 0.03, 0], [0.15, 0.0, 0], [0.16, 0.01, 0.0]])
    keep, inverse = voxel_downsample(xyz, 0.1)
    # voxels: points 0,1 share (0,0,0); points 2,3 share (1,0,0)
    assert len(keep) == 2
    assert inverse[0] == inverse[1] != inverse[2] == inverse[3]
    np.testing.assert_array_equal(xyz[keep][inverse[[0, 2]]], xyz[keep])


def test_spatial_blocks_partition_and_respect_the_size():
    xyz = np.random.default_rng(0).uniform(0, 1, (1000, 3))
    blocks = spatial_blocks(xyz, 128)
    assert all(len(b) <= 128 for b in blocks)
    np.testing.assert_array_equal(np.sort(np.concatenate(blocks)), np.arange(1000))


def test_block_features_scale_by_radius_and_normalise_location():
    xyz = np.array([[1.0, 2.0, 3.0], [1.2, 2.1, 3.4]])
    f = block_features(xyz, part_radius=0.1)
    np.testing.assert_allclose(f[1, :3], [2.0, 1.0, 4.0], rtol=1e-6)   # (0.2, 0.1, 0.4) / 0.1
    np.testing.assert_allclose(f[1, 3:], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(f[0], 0.0)


def test_knn_graph_starts_with_self_and_pads_small_blocks():
    xyz = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
    knn = knn_graph(xyz, 4)
    assert knn.shape == (3, 4)
    assert knn[:, 0].tolist() == [0, 1, 2]
    assert knn[0].tolist() == [0, 1, 2, 2]   # padded with its farthest neighbour


def test_dominant_plane_takes_the_floor_and_spares_parts_above_it():
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-1, 1, (3000, 2)), rng.normal(0, 0.001, 3000)]
    part = np.c_[rng.uniform(-0.1, 0.1, (500, 2)), rng.uniform(0.02, 0.08, 500)]
    on_floor = dominant_plane(np.vstack([floor, part]), tolerance=0.005)
    assert on_floor[:3000].mean() > 0.99
    assert not on_floor[3000:].any()


def test_dominant_plane_removes_nothing_when_no_plane_is_large():
    rng = np.random.default_rng(2)
    pile = rng.uniform(0, 1, (2000, 3))
    assert not dominant_plane(pile, tolerance=0.005).any()


def test_plane_tolerance_is_bounded():
    assert plane_tolerance(0.001) == 0.004 and plane_tolerance(10.0) == 0.012
    assert plane_tolerance(0.08) == 0.008


def test_bounded_downsample_caps_network_points_and_keeps_the_mapping():
    from fpcc_ros.pipeline import _bounded_downsample
    rng = np.random.default_rng(3)
    cube = rng.uniform(0, 0.5, (200_000, 3))          # a dense volume, not a surface
    keep, inverse, voxel = _bounded_downsample(cube, 0.004, max_points=5000)
    assert len(keep) <= 5000 and voxel > 0.004
    # every input point maps to a representative in its own (coarser) voxel
    assert np.abs(cube[keep][inverse] - cube).max() <= np.sqrt(3) * voxel
    small_keep, _, small_voxel = _bounded_downsample(cube[:1000], 0.004, max_points=5000)
    assert small_voxel == 0.004 and len(small_keep) <= 1000


def test_dilated_neighbourhood_keeps_the_nearest_and_spreads_the_rest():
    from fpcc_ros.features import neighbour_columns
    cols = neighbour_columns(k=6, near=3, reach=12)
    assert cols.tolist() == [0, 1, 2, 3, 7, 11]          # 3 nearest, then 3 spread over 3..11
    assert neighbour_columns(16, 0, 0).tolist() == list(range(16))   # plain kNN
    xyz = np.c_[np.arange(20.0), np.zeros(20), np.zeros(20)]        # points on a line, 1 apart
    graph = knn_graph(xyz, 6, near=3, reach=12)
    plain = knn_graph(xyz, 12)
    np.testing.assert_array_equal(graph, plain[:, [0, 1, 2, 3, 7, 11]])
    assert graph[:, 0].tolist() == list(range(20))      # itself first


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_column_bounds_and_block_features_match_the_axis_reductions(dtype):
    from fpcc_ros.features import block_features, column_bounds

    xyz = np.random.default_rng(4).normal(size=(777, 3)).astype(dtype) * [1.0, 3.0, 0.01]
    lo, hi = column_bounds(xyz)
    np.testing.assert_array_equal(lo, xyz.min(axis=0))
    np.testing.assert_array_equal(hi, xyz.max(axis=0))
    shifted = xyz - xyz.min(axis=0)   # the definition, bit for bit
    want = np.concatenate([shifted / 0.05, shifted / shifted.max(axis=0)], axis=1)
    np.testing.assert_array_equal(block_features(xyz, 0.05), want.astype(np.float32))


def test_tile_order_groups_image_rows_into_compact_tiles():
    # a 64 x 48 grid in image order: 256 consecutive rows are a strip four image rows high
    v, u = np.mgrid[0:48, 0:64]
    xyz = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1).astype(np.float64)
    order = tile_order(xyz, 256)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(xyz)))   # a permutation
    tiled = xyz[order]
    for start in range(0, len(xyz) - 255, 256):
        extent = np.ptp(tiled[start:start + 256], axis=0)
        assert extent[0] < 40 and extent[1] < 40, (start, extent)         # a strip: 63 x 3
    assert (tile_order(np.zeros((10, 3)), 4) == np.arange(10)).all()      # no extent: as is
    assert len(tile_order(np.zeros((0, 3)), 4)) == 0
