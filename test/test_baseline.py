"""The clustering baselines (Euclidean, DBSCAN) and their sweep on hand-built scenes whose right
answer is known by design."""
import numpy as np
import pytest

from fpcc_ros.baseline import dbscan_clusters, euclidean_clusters, find_planes, foreground_mask
from fpcc_ros.baseline_sweep import METHODS, Grid, choose, sweep_scene
from fpcc_ros.metrics import f1_score, scene_counts

STEP = 0.005  # grid spacing of every synthetic surface / solid (m)


def grid(lo, hi, step=STEP) -> np.ndarray:
    """Regular grid of points filling the box lo..hi (a flat box gives a plane patch)."""
    axes = [np.arange(a, b + step / 2, step) if b > a else np.array([a]) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def cube(corner, size=0.04) -> np.ndarray:
    corner = np.asarray(corner, float)
    return grid(corner, corner + size)


def scene(*parts: np.ndarray, background: tuple[np.ndarray, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate background (label 0) and parts (labels 1..K)."""
    chunks = list(background) + list(parts)
    labels = [np.zeros(len(b), int) for b in background] + \
             [np.full(len(p), i + 1) for i, p in enumerate(parts)]
    return np.concatenate(chunks), np.concatenate(labels)


def same_partition(pred: np.ndarray, gt: np.ndarray) -> bool:
    """pred equals gt up to renumbering, with 0 (no instance) mapped to 0."""
    pairs = np.unique(np.stack([gt, pred], 1), axis=0)
    return (len(pairs) == len(np.unique(gt)) == len(np.unique(pred))
            and all((p == 0) == (g == 0) for g, p in pairs))


FLOOR = grid((0.0, 0.0, 1.0), (0.4, 0.4, 1.0))
CUBES = [cube((0.05, 0.05, 1.02)), cube((0.25, 0.08, 1.03)), cube((0.12, 0.28, 1.02))]


def test_separates_blobs_and_removes_floor():
    xyz, gt = scene(*CUBES, background=(FLOOR,))
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None)
    assert labels.shape == (len(xyz),) and labels.dtype == np.uint32
    assert (labels[gt == 0] == 0).all()          # every floor point removed
    assert same_partition(labels, gt)            # three cubes, three labels, nothing lost
    assert sorted(np.bincount(labels)[1:]) == sorted(len(c) for c in CUBES)


def test_voxel_downsampling_carries_labels_to_every_point():
    xyz, gt = scene(*CUBES, background=(FLOOR,))
    labels = euclidean_clusters(xyz, tolerance=0.012, min_points=20, voxel_size=0.004)
    assert same_partition(labels, gt)


def test_touching_blobs_merge():
    """The known failure: parts closer than the tolerance become one cluster."""
    a = cube((0.05, 0.05, 1.02))
    b = cube((0.05 + 0.04 + 0.003, 0.05, 1.02))   # 3 mm gap to a
    c = cube((0.25, 0.25, 1.02))
    xyz, _ = scene(a, b, c, background=(FLOOR,))
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None)
    la, lb, lc = (labels[len(FLOOR) + o: len(FLOOR) + o + len(a)]
                  for o in (0, len(a), 2 * len(a)))
    assert len(np.unique(la)) == 1 and la[0] > 0
    assert (lb == la[0]).all()                   # merged with a
    assert (lc > 0).all() and (lc != la[0]).all()
    assert labels.max() == 2


def test_nan_points_get_zero_and_do_not_disturb_the_rest():
    xyz, gt = scene(*CUBES, background=(FLOOR,))
    rng = np.random.default_rng(0)
    holes = rng.choice(len(xyz), 500, replace=False)
    xyz = xyz.copy()
    xyz[holes] = np.nan
    xyz[holes[:10], 0] = 0.1                     # partly NaN rows count as no return too
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None)
    assert (labels[holes] == 0).all()
    keep = np.setdiff1d(np.arange(len(xyz)), holes)
    assert same_partition(labels[keep], gt[keep])
    all_nan = np.full((50, 3), np.nan)
    assert (euclidean_clusters(all_nan, 0.01, 1, None) == 0).all()
    assert euclidean_clusters(np.zeros((0, 3)), 0.01, 1, None).shape == (0,)


def test_small_clusters_dropped_and_roi_crops():
    speck = cube((0.3, 0.3, 1.05), size=0.005)   # 2x2x2 = 8 points
    xyz, gt = scene(*CUBES, speck, background=(FLOOR,))
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None)
    assert (labels[gt == 4] == 0).all()
    assert labels.max() == 3
    roi = ((0.0, 0.0, 0.9), (0.2, 0.4, 1.2))     # x <= 0.2: cubes 1 and 3 only
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None, roi=roi)
    assert (labels[gt == 2] == 0).all()
    assert same_partition(labels[np.isin(gt, [1, 3])], gt[np.isin(gt, [1, 3])])


def test_no_plane_removed_without_a_dominant_one():
    """A pile without visible floor: no plane holds 8 % of the points, nothing is removed.
    (A 5 mm slab through one of six 4 cm cubes holds at most 3/9 of it: 5.6 % of the points.)"""
    pile = [cube((x, y, z)) for x, y, z in [(0.0, 0.0, 1.0), (0.07, 0.0, 1.01), (0.14, 0.0, 1.025),
                                            (0.0, 0.07, 1.04), (0.07, 0.07, 1.005), (0.14, 0.07, 1.03)]]
    xyz, gt = scene(*pile)
    mask, planes = foreground_mask(xyz, plane_tolerance=0.005)
    assert planes == [] and mask.all()
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None)
    assert (labels > 0).all() and same_partition(labels, gt)


def test_coplanar_but_separate_flat_parts_are_not_a_floor():
    """16 flat squares at one height: one plane holds every point, but in 16 small pieces."""
    squares = [grid((x, y, 1.05), (x + 0.02, y + 0.02, 1.05), 0.002)
               for x in np.arange(4) * 0.05 for y in np.arange(4) * 0.05]
    xyz, gt = scene(*squares)
    assert find_planes(xyz, 0.005) == []
    labels = euclidean_clusters(xyz, tolerance=0.005, min_points=20, voxel_size=None)
    assert same_partition(labels, gt) and labels.max() == 16


def test_tote_floor_and_walls_removed():
    """Floor 0.4 x 0.3 m and four 0.1 m walls: all five planes go, the cubes inside stay."""
    floor = grid((0, 0, 0), (0.4, 0.3, 0))
    walls = (grid((0, 0, STEP), (0, 0.3, 0.1)), grid((0.4, 0, STEP), (0.4, 0.3, 0.1)),
             grid((STEP, 0, STEP), (0.4 - STEP, 0, 0.1)), grid((STEP, 0.3, STEP), (0.4 - STEP, 0.3, 0.1)))
    parts = [cube((0.05, 0.05, 0.02)), cube((0.2, 0.12, 0.025)), cube((0.3, 0.22, 0.02))]
    xyz, gt = scene(*parts, background=(floor, *walls))
    mask, planes = foreground_mask(xyz, plane_tolerance=0.003)
    normals = np.abs(np.array([p.normal for p in planes]))
    assert len(planes) == 5
    assert normals[0] == pytest.approx([0, 0, 1], abs=1e-6)           # the floor first
    assert sorted(np.argmax(normals[1:], axis=1)) == [0, 0, 1, 1]      # walls: two x, two y
    assert not mask[gt == 0].any() and mask[gt > 0].all()
    labels = euclidean_clusters(xyz, tolerance=0.01, min_points=20, voxel_size=None,
                                plane_tolerance=0.003)
    assert same_partition(labels, gt)


# -- DBSCAN and the sweep -------------------------------------------------------------------------
# A case whose best setting is known by construction (5 mm grid, solid 4 cm cubes of 9^3 = 729
# points, 2 cm above a floor that plane removal takes):
#   A, B  8 mm apart face to face: a link distance of 10 mm merges them, 6 mm keeps them apart;
#   C, D  30 mm apart, joined by a bridge of 5 background points 5 mm apart (label 0): at eps
#         6 mm a bridge point has 3 points within eps (itself and two neighbours; the end ones a
#         bridge and a cube point), a cube point 4 (corner) to 7 (inside), one more where the
#         bridge touches. min_samples 5: every cube point is core or borders one, the bridge is
#         noise except its two ends (borders of C and D): C and D apart. min_samples 1 (and
#         Euclidean clustering at any tolerance that links the cubes' own grid) joins them;
#   E     a chip of 3^3 = 27 points far away (label 0): a cluster of its own unless clusters
#         under 50 points are dropped (1000 would drop the cubes too).
# At 3 mm nothing links (the grid is 5 mm); at 6 mm no point is core at min_samples 20 (7 at
# most); at 10 mm A and B merge.
BEST_DBSCAN = (0.006, 5, 50)


def bridge_scene() -> tuple[np.ndarray, np.ndarray]:
    a, b = cube((0.05, 0.05, 1.02)), cube((0.05 + 0.04 + 0.008, 0.05, 1.02))
    c, d = cube((0.05, 0.25, 1.02)), cube((0.05 + 0.04 + 0.03, 0.25, 1.02))
    bridge = np.c_[0.09 + 0.005 * np.arange(1, 6), np.full(5, 0.27), np.full(5, 1.04)]
    chip = cube((0.32, 0.32, 1.03), size=0.01)
    return scene(a, b, c, d, background=(FLOOR, bridge, chip))


def test_dbscan_baseline_splits_a_sparse_bridge_that_euclidean_follows():
    xyz, gt = bridge_scene()
    labels = dbscan_clusters(xyz, *BEST_DBSCAN, plane_tolerance=0.0025)
    parts = gt > 0
    assert same_partition(labels[parts], gt[parts])          # A, B, C, D: four clusters
    assert labels.max() == 4                                  # chip dropped, bridge not a part
    assert (labels[:len(FLOOR)] == 0).all()                   # floor removed
    euclid = euclidean_clusters(xyz, 0.006, 50, None, plane_tolerance=0.0025)
    assert euclid.max() == 3                                  # A, B and C+D through the bridge
    assert len(np.unique(euclid[np.isin(gt, [3, 4])])) == 1


def _tuned(methods, grid):
    xyz, gt = bridge_scene()
    mask, _ = foreground_mask(xyz, 0.0025)
    finite = np.ones(len(xyz), bool)
    counts = sweep_scene(xyz, mask, gt, finite, ["paper"], 300, grid, methods)
    return xyz, gt, mask, counts


def test_sweep_picks_the_known_best_dbscan_setting():
    grid = Grid((0.003, 0.006, 0.01), (1, 5, 20), (1, 50, 1000))
    _, _, _, counts = _tuned(["dbscan"], grid)
    assert len(counts) == 27
    best = choose(counts, "dbscan", "paper")
    assert (best.distance, best.min_samples, best.min_cluster_size) == BEST_DBSCAN
    c = counts[best]["paper"]
    assert (c.true_positives, c.predictions, c.ground_truths) == (4, 4, 4)
    assert sum(f1_score(v["paper"]) == 1.0 for v in counts.values()) == 1   # the only perfect one


def test_sweep_tunes_the_euclidean_minimum_cluster_size():
    """Euclidean clustering at 6 mm: A, B and C+D (IoU 729/1463 with C or D: no match); the chip
    is a fourth cluster unless the minimum size (50) drops it: TP 2, pred 3, GT 4, F1 4/7
    (with the chip, pred 4: F1 1/2)."""
    grid = Grid((0.003, 0.006, 0.01), (1, 5, 20), (1, 50, 1000))
    _, _, _, counts = _tuned(["euclidean"], grid)
    assert {s.min_samples for s in counts} == {1} and len(counts) == 9
    best = choose(counts, "euclidean", "paper")
    assert (best.distance, best.min_cluster_size) == (0.006, 50)
    assert f1_score(counts[best]["paper"]) == pytest.approx(4 / 7)
    keep_chip = next(s for s in counts if (s.distance, s.min_cluster_size) == (0.006, 1))
    assert f1_score(counts[keep_chip]["paper"]) == pytest.approx(1 / 2)


def test_sweep_counts_match_running_each_setting():
    """The sweep scores minimum sizes by dropping rows of one IoU matrix; running each setting
    and scoring its labels from scratch (fpcc_ros.metrics.scene_counts) must agree."""
    grid = Grid((0.006, 0.01), (1, 5), (1, 50, 800))
    xyz, gt, mask, counts = _tuned(METHODS, grid)
    for setting, by_protocol in counts.items():
        assert by_protocol["paper"] == scene_counts(setting.run(xyz, mask), gt, "paper")


def test_grid_rejects_nonsense_with_the_field_named():
    with pytest.raises(ValueError, match="min_samples"):
        Grid((0.006,), (0,), (1,))
    with pytest.raises(ValueError, match="distances"):
        Grid((-0.006,), (1,), (1,))
