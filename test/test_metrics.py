"""Evaluation metrics on scenes small enough to count by hand."""
import numpy as np
import pytest

from fpcc_ros.metrics import InstanceCounts, scene_counts


def test_perfect_prediction_with_permuted_ids():
    gt = np.array([0, 1, 1, 1, 2, 2, 2, 2])
    pred = np.array([0, 7, 7, 7, 3, 3, 3, 3])
    c = scene_counts(pred, gt, protocol="paper")
    assert (c.true_positives, c.predictions, c.ground_truths) == (3 - 1, 2, 2)
    assert c.precision == 1.0 and c.recall == 1.0 and c.mucov == 1.0 and c.mwcov == 1.0


def test_background_inside_a_prediction_counts_against_iou():
    # GT instance 1 has 2 points; the prediction covers them plus 3 background points:
    # IoU = 2 / 5 = 0.4 < 0.5 -> no match.
    gt = np.array([1, 1, 0, 0, 0])
    pred = np.array([1, 1, 1, 1, 1])
    c = scene_counts(pred, gt, protocol="paper")
    assert c.true_positives == 0 and c.predictions == 1 and c.ground_truths == 1
    assert c.mucov == pytest.approx(0.4)


def test_merged_prediction_matches_at_most_one_instance():
    # GT: A = 4 points, B = 2 points. One prediction covers both: IoU(A) = 4/6, IoU(B) = 2/6.
    gt = np.array([1, 1, 1, 1, 2, 2])
    pred = np.ones(6, int)
    c = scene_counts(pred, gt, protocol="paper")
    assert c.true_positives == 1 and c.precision == 1.0 and c.recall == 0.5
    assert c.mucov == pytest.approx((4 / 6 + 2 / 6) / 2)
    assert c.mwcov == pytest.approx((4 * 4 / 6 + 2 * 2 / 6) / 6)


def test_visible_protocol_removes_small_instances_points_and_all():
    # GT 1 has 5 points, GT 2 has 2 (below min_visible=3). The prediction that covers GT 2 and
    # nothing else vanishes with those points; prediction 9 covers GT 1 plus GT 2's points, which
    # are removed, so it matches GT 1 exactly.
    gt = np.array([1, 1, 1, 1, 1, 2, 2])
    pred = np.array([9, 9, 9, 9, 9, 9, 4])
    paper = scene_counts(pred, gt, protocol="paper")
    # paper: pred 9 vs GT 1: IoU 5/6; pred 4 vs GT 2: IoU 1/2 = 0.5 -> both match
    assert (paper.true_positives, paper.predictions, paper.ground_truths) == (2, 2, 2)
    visible = scene_counts(pred, gt, protocol="visible", min_visible=3)
    assert (visible.true_positives, visible.predictions, visible.ground_truths) == (1, 1, 1)


def test_counts_sum_over_scenes_before_dividing():
    a = InstanceCounts(true_positives=1, predictions=1, ground_truths=4)
    b = InstanceCounts(true_positives=3, predictions=5, ground_truths=4)
    total = a + b
    assert total.precision == pytest.approx(4 / 6) and total.recall == pytest.approx(4 / 8)
