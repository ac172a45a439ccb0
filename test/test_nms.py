"""NMS (paper Algorithm 1) on hand-built cases whose answers are worked out in the comments."""
import numpy as np
import pytest

from fpcc_ros.nms import nms_centers, nms_reference

IMPLEMENTATIONS = [nms_centers, nms_reference]


def _line(xs):
    return np.array([[x, 0.0, 0.0] for x in xs])


@pytest.mark.parametrize("nms", IMPLEMENTATIONS)
def test_two_separated_blobs_give_their_planted_peaks(nms):
    xyz = _line([0.0, 0.1, 0.2, 1.0, 1.05, 2.0])
    scores = np.array([0.9, 0.95, 0.5, 0.8, 0.85, 0.55])
    # candidates (> 0.6): 0, 1, 3, 4. Best is 1 (0.95): suppresses 0 (0.1 away).
    # Next best 4 (0.85): suppresses 3 (0.05 away). Point 5 never is a candidate.
    assert nms(xyz, scores, 0.6, 0.3).tolist() == [1, 4]


@pytest.mark.parametrize("nms", IMPLEMENTATIONS)
def test_threshold_is_strict_and_radius_inclusive(nms):
    xyz = _line([0.0, 0.3, 0.61, 5.0])
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    # 3 scores exactly 0.6 -> not a candidate. 1 is exactly 0.3 from 0 -> suppressed (<=).
    # 2 is 0.61 from 0 -> survives.
    assert nms(xyz, scores, 0.6, 0.3).tolist() == [0, 2]


@pytest.mark.parametrize("nms", IMPLEMENTATIONS)
def test_no_candidates_returns_empty(nms):
    xyz = _line([0.0, 1.0])
    assert nms(xyz, np.array([0.1, 0.2]), 0.6, 0.3).tolist() == []


@pytest.mark.parametrize("nms", IMPLEMENTATIONS)
def test_suppression_is_not_transitive(nms):
    # 0 suppresses 1 (0.25 away), but 2 (0.5 from 0) is only near the suppressed 1: it stays.
    xyz = _line([0.0, 0.25, 0.5])
    scores = np.array([0.9, 0.8, 0.7])
    assert nms(xyz, scores, 0.6, 0.3).tolist() == [0, 2]


@pytest.mark.parametrize("seed", range(5))
def test_fast_matches_literal_algorithm_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 1, (400, 3))
    scores = rng.uniform(0, 1, 400)
    expected = nms_reference(xyz, scores, 0.6, 0.15)
    assert len(expected) > 3
    np.testing.assert_array_equal(nms_centers(xyz, scores, 0.6, 0.15), expected)
