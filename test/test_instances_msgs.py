"""PoseArray / MarkerArray for instances, and the shared palette (both message flavours)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from msg_tools import palette
from msg_tools.instances import create_instance_markers, create_pose_array
from msg_tools.msg_types import RCLPY, ROSBAGS, msgtype_of

FLAVOURS = [pytest.param(RCLPY, id="rclpy"), pytest.param(ROSBAGS, id="rosbags")]
CENTROIDS = np.array([[0.1, 0.2, 0.9], [-0.3, 0.0, 1.1], [0.5, -0.4, 1.0]])
COUNTS = [1520, 301, 77]


@pytest.mark.parametrize("types", FLAVOURS)
def test_pose_array(types):
    msg = create_pose_array(types.header("cam", 5, 6), CENTROIDS, types)
    assert msgtype_of(msg) == "geometry_msgs/msg/PoseArray"
    assert msg.header.frame_id == "cam" and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (5, 6)
    assert len(msg.poses) == 3
    for pose, c in zip(msg.poses, CENTROIDS):
        assert (pose.position.x, pose.position.y, pose.position.z) == tuple(c)
        q = pose.orientation
        assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    assert create_pose_array(types.header(), np.zeros((0, 3)), types).poses == []


@pytest.mark.parametrize("types", FLAVOURS)
def test_instance_markers(types):
    header = RCLPY.header("cam", 1700000000, 42)  # header of the other flavour is converted
    msg = create_instance_markers(header, CENTROIDS, COUNTS, types, ns="fpcc", sphere_diameter=0.03)
    assert msgtype_of(msg) == "visualization_msgs/msg/MarkerArray"
    markers = msg.markers
    assert len(markers) == 1 + 2 * 3
    assert markers[0].action == 3  # DELETEALL first
    for m in markers:
        assert m.header.frame_id == "cam"
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1700000000, 42)
        assert m.ns == "fpcc"
    spheres = [m for m in markers[1:] if m.type == 2]
    texts = [m for m in markers[1:] if m.type == 9]
    assert len(spheres) == 3 and len(texts) == 3
    assert len({m.id for m in markers[1:]}) == 6  # unique ids
    first_colour = (0xF3 / 255, 0xC3 / 255, 0x00 / 255)  # palette entry of label 1, by hand
    for i, (s, t) in enumerate(zip(spheres, texts)):
        label = i + 1
        assert s.action == 0 and t.action == 0
        assert (s.pose.position.x, s.pose.position.y, s.pose.position.z) == tuple(CENTROIDS[i])
        assert (s.scale.x, s.scale.y, s.scale.z) == (0.03, 0.03, 0.03)
        rgb = tuple(int(v) for v in palette.PALETTE[i])
        for m in (s, t):
            assert math.isclose(m.color.r, rgb[0] / 255) and math.isclose(m.color.g, rgb[1] / 255)
            assert math.isclose(m.color.b, rgb[2] / 255) and m.color.a == 1.0
        assert t.text == f"{label} ({COUNTS[i]} pts)"
        assert t.scale.z > 0
    assert (spheres[0].color.r, spheres[0].color.g, spheres[0].color.b) == pytest.approx(first_colour)
    # ids are a function of the label only: the same label keeps its ids in the next frame
    again = create_instance_markers(header, CENTROIDS[:2], COUNTS[:2], types)
    assert [m.id for m in again.markers[1:]] == [m.id for m in markers[1:5]]


@pytest.mark.parametrize("types", FLAVOURS)
def test_markers_for_no_instances_and_nan_centroid(types):
    only_delete = create_instance_markers(types.header(), np.zeros((0, 3)), [], types)
    assert [m.action for m in only_delete.markers] == [3]
    cents = CENTROIDS.copy()
    cents[1] = np.nan
    msg = create_instance_markers(types.header(), cents, COUNTS, types)
    assert len(msg.markers) == 1 + 2 * 2
    assert [m.text for m in msg.markers if m.type == 9] == ["1 (1520 pts)", "3 (77 pts)"]
    with pytest.raises(ValueError, match="point_counts has 2 entries"):
        create_instance_markers(types.header(), CENTROIDS, COUNTS[:2], types)


def test_rclpy_markers_serialize():
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    msg = create_instance_markers(RCLPY.header("cam", 1, 2), CENTROIDS, COUNTS, RCLPY)
    back = deserialize_message(serialize_message(msg), MarkerArray)
    assert back.markers[2].text == "1 (1520 pts)"


def test_rosbags_markers_serialize():
    store = ROSBAGS.typestore
    msg = create_instance_markers(ROSBAGS.header("cam", 1, 2), CENTROIDS, COUNTS, ROSBAGS)
    raw = store.serialize_cdr(msg, "visualization_msgs/msg/MarkerArray")
    back = store.deserialize_cdr(raw, "visualization_msgs/msg/MarkerArray")
    assert back.markers[4].text == "2 (301 pts)"


# -- palette ------------------------------------------------------------------------------------
def test_palette_background_and_wrap():
    n = len(palette.PALETTE)
    assert 16 <= n <= 32
    labels = np.array([0, 1, 2, n, n + 1, -1])
    cols = palette.label_colors(labels)
    assert cols.dtype == np.uint8 and cols.shape == (6, 3)
    assert tuple(cols[0]) == (128, 128, 128) and tuple(cols[5]) == (128, 128, 128)
    assert tuple(cols[1]) == (0xF3, 0xC3, 0x00)
    assert tuple(cols[4]) == tuple(cols[1])  # label n+1 wraps to the first colour
    assert tuple(cols[3]) == tuple(palette.PALETTE[-1])
    packed = palette.packed_rgb(labels)
    assert packed.dtype == np.uint32
    expected = [(int(r) << 16) | (int(g) << 8) | int(b) for r, g, b in cols]
    assert packed.tolist() == expected
    assert packed[0] == 0x808080 and packed[1] == 0xF3C300
    assert palette.instance_color(0) == (128 / 255, 128 / 255, 128 / 255)
    assert palette.instance_color(1) == pytest.approx((0xF3 / 255, 0xC3 / 255, 0.0))
    assert palette.label_colors(np.zeros((2, 3), int)).shape == (2, 3, 3)


def test_palette_colours_are_distinct():
    cols = np.vstack([palette.PALETTE, [palette.BACKGROUND]]).astype(float)
    d = np.linalg.norm(cols[:, None] - cols[None], axis=-1)
    d[np.arange(len(cols)), np.arange(len(cols))] = np.inf
    assert d.min() > 38, "two palette colours (or one and the background grey) are nearly equal"
