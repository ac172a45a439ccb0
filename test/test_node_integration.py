"""The live node in its own process, over DDS, fed from the bundled demo bag.

Per input message: exactly one output on each topic with the input's header; the cloud keeps
height, width and point order; labels only where xyz is finite; one pose per distinct label;
markers are a DELETEALL plus a sphere and a text per instance at the poses.
"""
import json

import numpy as np
import pytest
import rclpy

from msg_tools.point_cloud2 import read_points, read_xyz
from msg_tools.msg_types import stamp_ns
from fpcc_ros.replay import CloudClient, NodeProcess, bag_clouds_as_rclpy

from conftest import REPO, TEST_DATA

pytestmark = pytest.mark.ros
DEMO_BAG = REPO / "bags" / "demo"
MODEL = TEST_DATA / "tiny_fpcc.onnx"
PART_RADIUS = json.loads((REPO / "bags" / "demo.json").read_text())["part_radius"]


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    clouds = bag_clouds_as_rclpy(DEMO_BAG)
    assert len(clouds) >= 2
    log = tmp_path_factory.mktemp("node") / "node.log"
    rclpy.init()
    try:
        with NodeProcess(["-p", f"model:={MODEL}", "-p", "min_points:=1",
                          "-p", f"part_radius:={PART_RADIUS}"], log_path=log) as node:
            client = CloudClient()
            try:
                assert client.wait_connected(timeout=60), node.log()
                records = []
                for _, cloud in clouds:
                    rec = client.send(cloud)
                    assert client.wait_complete(rec, timeout=60), node.log()
                    records.append(rec)
                # give stray duplicates a moment to show up before we count them
                import time
                time.sleep(1.0)
                unmatched = list(client.unmatched)
            finally:
                client.close()
            code = node.stop()
    finally:
        rclpy.try_shutdown()
    return records, unmatched, code


def test_one_output_per_topic_per_input_with_the_input_header(replayed):
    records, unmatched, code = replayed
    assert unmatched == []
    assert code == 0
    for rec in records:
        assert rec.complete
        for name in ("segmented_points", "instances"):
            header = rec.outputs[name].header
            assert stamp_ns(header) == stamp_ns(rec.input.header)
            assert header.frame_id == rec.input.header.frame_id
        for marker in rec.outputs["instance_markers"].markers:
            assert stamp_ns(marker.header) == stamp_ns(rec.input.header)
            assert marker.header.frame_id == rec.input.header.frame_id


def test_segmented_cloud_is_index_aligned_and_labels_only_finite_points(replayed):
    for rec in replayed[0]:
        out, inp = rec.outputs["segmented_points"], rec.input
        assert (out.height, out.width) == (inp.height, inp.width)
        assert out.point_step == 24 and len(out.data) == out.row_step * out.height
        xyz_in = read_xyz(inp)
        pts = read_points(out)
        finite = np.isfinite(xyz_in).all(axis=1)
        np.testing.assert_array_equal(np.isfinite(read_xyz(out)).all(axis=1), finite)
        np.testing.assert_allclose(read_xyz(out)[finite], xyz_in[finite], atol=1e-6)
        assert not pts["label"][~finite].any()


def test_instances_and_markers_match_the_labels(replayed):
    for rec in replayed[0]:
        pts = read_points(rec.outputs["segmented_points"])
        xyz = read_xyz(rec.outputs["segmented_points"])
        distinct = np.unique(pts["label"][pts["label"] > 0])
        poses = rec.outputs["instances"].poses
        assert len(poses) == len(distinct)
        assert distinct.tolist() == list(range(1, len(distinct) + 1))
        for i, pose in enumerate(poses):
            expected = xyz[pts["label"] == i + 1].astype(np.float64).mean(axis=0)
            np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z],
                                       expected, atol=1e-4)
            assert pose.orientation.w == 1.0
        markers = rec.outputs["instance_markers"].markers
        assert markers[0].action == 3  # DELETEALL
        spheres = [m for m in markers[1:] if m.type == 2]
        texts = [m for m in markers[1:] if m.type == 9]
        assert len(spheres) == len(texts) == len(distinct)
        for sphere, pose in zip(spheres, poses):
            assert sphere.pose.position.x == pytest.approx(pose.position.x)
