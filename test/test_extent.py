"""extent.group_widths: the size the connected clustering compares with a part's diameter."""
import numpy as np
import pytest

from fpcc_ros.extent import fit_within, group_widths


def test_a_segment_is_as_wide_as_its_longest_shadow_on_the_thirteen_directions():
    # (0,0,0) -> (2,1,0), 2.236 long: its shadows are 2 on x, 3/sqrt(2) = 2.121 on (1,1,0),
    # 3/sqrt(3) = 1.732 on (1,1,1), less on the others
    points = np.linspace(0.0, 1.0, 11)[:, None] * np.array([2.0, 1.0, 0.0])
    width = group_widths(points, np.ones(11, int), 1)
    assert width[1] == pytest.approx(3.0 / np.sqrt(2.0))
    assert width[0] == 0.0    # group 0 has no points


def test_a_ball_is_never_wider_than_its_diameter_though_its_box_diagonal_is():
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(4000, 3))
    points = 0.5 * directions / np.linalg.norm(directions, axis=1, keepdims=True)  # radius 0.5
    width = group_widths(points, np.ones(len(points), int), 1)[1]
    diagonal = np.linalg.norm(points.max(axis=0) - points.min(axis=0))
    assert 0.886 * 1.0 <= width <= 1.0 + 1e-9
    assert diagonal > 1.6      # ~sqrt(3): a box test would call the ball bigger than itself


def test_groups_are_measured_apart_whatever_order_their_rows_come_in():
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]])           # 3 along z
    b = np.array([[5.0, 5.0, 5.0], [5.5, 5.0, 5.0]])           # 0.5 along x
    points = np.vstack([a[:1], b[:1], a[1:], b[1:]])
    width = group_widths(points, np.array([2, 4, 2, 4]), 5)
    np.testing.assert_allclose(width, [0.0, 0.0, 3.0, 0.0, 0.5, 0.0])
    np.testing.assert_array_equal(group_widths(np.zeros((0, 3)), np.zeros(0, int), 2), [0, 0, 0])


def test_fit_within_answers_as_the_widths_do_on_each_side_of_the_limit():
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(2000, 3))
    ball = 0.5 * directions / np.linalg.norm(directions, axis=1, keepdims=True)  # width ~1
    small = 0.1 * ball + 10.0                       # box diagonal < 1.1: fits without measuring
    rod = np.linspace(0.0, 2.0, 50)[:, None] * np.array([1.0, 0.0, 0.0]) - 10.0  # 2 long on x
    points = np.vstack([ball, small, rod])
    group = np.r_[np.full(len(ball), 1), np.full(len(small), 2), np.full(len(rod), 3)]
    # the ball's box diagonal (~1.7) is over 1.1 and its axis extents (~1) under it: measured
    fits = fit_within(points, group, 4, 1.1)
    np.testing.assert_array_equal(fits, [True, True, True, False, True])
    np.testing.assert_array_equal(fits, group_widths(points, group, 4) <= 1.1)
