"""DBSCAN semantics on hand-made clouds whose answer is worked out by hand."""
import numpy as np

from fpcc_ros.dbscan import dbscan


def _line(start: float, count: int, step: float = 1.0) -> np.ndarray:
    return np.c_[start + step * np.arange(count), np.zeros(count), np.zeros(count)]


def test_a_chain_of_core_points_is_one_cluster() -> None:
    # points 1 apart: each interior point has 3 within eps 1 (itself and two neighbours)
    labels = dbscan(_line(0, 10), eps=1.0, min_samples=3)
    assert (labels == 1).all()


def test_a_sparse_bridge_below_min_samples_splits_two_blobs() -> None:
    blob = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0.5, 0.5, 0]], float)
    left, right = blob, blob + [3.0, 0, 0]
    # two bridge points 1 apart, each 0.79 from two blob points: a chain at eps 1 ...
    bridge = np.array([[1.25, 0.25, 0], [2.25, 0.25, 0]])
    xyz = np.vstack([left, right, bridge])
    # ... but a bridge point has 4 points within eps (itself included), a blob's inner edge 5
    labels = dbscan(xyz, eps=1.0, min_samples=5)
    assert len(set(labels[:4])) == 1 and len(set(labels[4:8])) == 1
    assert labels[0] != labels[4] and labels[0] > 0 and labels[4] > 0
    # connectivity alone (min_samples 1) joins them through the bridge
    assert len(set(dbscan(xyz, eps=1.0, min_samples=1))) == 1


def test_border_points_join_and_isolated_points_are_noise() -> None:
    core = _line(0, 5, 0.5)                  # dense: 5 points 0.5 apart
    border = np.array([[2.9, 0, 0]])          # within eps 1 of the last core point only
    noise = np.array([[10.0, 0, 0]])
    labels = dbscan(np.vstack([core, border, noise]), eps=1.0, min_samples=3)
    assert (labels[:6] == 1).all() and labels[6] == 0


def test_min_cluster_size_drops_a_fragment_and_numbers_by_size() -> None:
    xyz = np.vstack([_line(0, 3), _line(100, 8)])
    labels = dbscan(xyz, eps=1.0, min_samples=1, min_cluster_size=4)
    assert (labels[:3] == 0).all() and (labels[3:] == 1).all()
    both = dbscan(xyz, eps=1.0, min_samples=1)
    assert (both[3:] == 1).all() and (both[:3] == 2).all()   # larger first


def test_weights_count_density_in_represented_points() -> None:
    xyz = _line(0, 2, 0.5)
    assert (dbscan(xyz, eps=1.0, min_samples=5) == 0).all()
    assert (dbscan(xyz, eps=1.0, min_samples=5, weights=np.array([3, 2])) == 1).all()
