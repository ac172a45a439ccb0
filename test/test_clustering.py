"""Nearest-center clustering with the d_max noise rule, on cases worked out by hand."""
import numpy as np
import pytest

from fpcc_ros import clustering
from fpcc_ros.clustering import assign_reference, assign_to_centers, single_thread_blas

# Two centers: index 0 at x=0 with embedding (0, 0); index 1 at x=1 with embedding (5, 0).
XYZ = np.array([
    [0.0, 0, 0],    # 0: center A
    [1.0, 0, 0],    # 1: center B
    [0.1, 0, 0],    # 2: near A in space and features          -> 1
    [0.9, 0, 0],    # 3: near B in space and features          -> 2
    [3.0, 0, 0],    # 4: beyond d_max of both                    -> 0
    [0.2, 0, 0],    # 5: features say B, but B is 0.8 > d_max away -> paper 0
    [0.05, 0, 0],   # 6: near A in space, embedding 2.0 from A (gate test)
])
EMB = np.array([[0, 0], [5, 0], [0.2, 0], [4.8, 0], [0.1, 0], [4.9, 0], [0, 2]], float)
CENTERS = np.array([0, 1])
D_MAX = 0.5


def test_reference_follows_the_paper_rule():
    labels = assign_reference(XYZ, EMB, CENTERS, D_MAX)
    assert labels.tolist() == [1, 2, 1, 2, 0, 0, 1]


def test_fast_agrees_with_reference_where_unambiguous():
    fast = assign_to_centers(XYZ, EMB, CENTERS, D_MAX)
    ref = assign_reference(XYZ, EMB, CENTERS, D_MAX)
    unambiguous = [0, 1, 2, 3, 4, 6]   # point 5's feature-nearest center is out of reach
    assert fast[unambiguous].tolist() == ref[unambiguous].tolist()
    # Point 5: the only center within d_max is A, so the gated rule picks A.
    assert fast[5] == 1


@pytest.mark.parametrize("assign", [assign_to_centers, assign_reference])
def test_feature_gate_rejects_points_far_in_feature_space(assign):
    labels = assign(XYZ, EMB, CENTERS, D_MAX, feature_gate=1.0)
    # point 6 is 2.0 from A in feature space; point 5 is 4.9 from A (fast) / B too far (ref)
    assert labels[6] == 0 and labels[5] == 0
    assert labels[[2, 3]].tolist() == [1, 2]


@pytest.mark.parametrize("assign", [assign_to_centers, assign_reference])
def test_no_centers_means_no_instances(assign):
    assert assign(XYZ, EMB, np.array([], dtype=np.int64), D_MAX).tolist() == [0] * len(XYZ)


@pytest.fixture(params=["blas", "numpy-loops"])
def products(request, monkeypatch):
    """Both ways of computing the center products: single-threaded BLAS, and numpy's loops used
    when threadpoolctl is missing."""
    if request.param == "numpy-loops":
        monkeypatch.setattr(clustering, "_blas_controller", lambda: None)
    else:
        assert clustering._blas_controller() is not None, "threadpoolctl is a pinned requirement"
    return request.param


@pytest.mark.parametrize("seed", range(4))
def test_fast_matches_reference_on_random_unambiguous_points(seed, products):
    rng = np.random.default_rng(seed)
    centers_xyz = rng.uniform(0, 4, (6, 3))
    centers_emb = rng.normal(0, 3, (6, 16))
    owner = rng.integers(0, 6, 300)
    xyz = np.vstack([centers_xyz, centers_xyz[owner] + rng.normal(0, 0.3, (300, 3))])
    emb = np.vstack([centers_emb, centers_emb[owner] + rng.normal(0, 0.5, (300, 16))])
    centers = np.arange(6)
    fast = assign_to_centers(xyz, emb, centers, 0.8)
    ref = assign_reference(xyz, emb, centers, 0.8)
    # unambiguous: the reference assigned the point (its feature-nearest center is within d_max)
    agree = ref > 0
    assert agree.sum() > 200
    np.testing.assert_array_equal(fast[agree], ref[agree])


def test_single_thread_blas_pins_blas_inside_the_block_only():
    from threadpoolctl import threadpool_info

    def blas_threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    np.ones((4, 4)) @ np.ones((4, 4))  # numpy's BLAS is loaded
    before = blas_threads()
    assert before, "no BLAS library found"
    with single_thread_blas():
        assert blas_threads() == {1}
    assert blas_threads() == before
