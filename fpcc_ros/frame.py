"""One frame, message in to messages out: decode -> pipeline -> encode.

Shared by the live node, the bag tool and the benchmark so all three run the same code.
Works with rclpy and rosbags message classes alike (``types`` picks the flavour to build).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from msg_tools.instances import create_instance_markers, create_pose_array
from msg_tools.point_cloud2 import create_segmented_cloud, read_xyz

from fpcc_ros.pipeline import Pipeline, SegmentationResult


@dataclass
class FrameOutputs:
    cloud: Any          # sensor_msgs/PointCloud2 -> segmented_points
    instances: Any      # geometry_msgs/PoseArray -> instances
    markers: Any        # visualization_msgs/MarkerArray -> instance_markers
    result: SegmentationResult

    @property
    def timings_ms(self) -> dict[str, float]:
        return self.result.timings_ms


def process_cloud(msg: Any, pipeline: Pipeline, types: Any) -> FrameOutputs:
    """Segment one PointCloud2. Raises ``CloudFormatError`` for a malformed message."""
    t0 = time.perf_counter()
    xyz = read_xyz(msg)  # validates first: CloudFormatError names the problem
    t_decode = time.perf_counter()

    result = pipeline.segment(xyz, (int(msg.height), int(msg.width)))  # height 1: no image
    t_segment = time.perf_counter()

    cloud = create_segmented_cloud(msg.header, xyz, result.labels, result.center_score,
                                   msg.height, msg.width, types=types)
    instances = create_pose_array(msg.header, result.centroids, types=types)
    markers = create_instance_markers(msg.header, result.centroids, result.point_counts,
                                      types=types)
    t_encode = time.perf_counter()

    result.timings_ms["decode"] = (t_decode - t0) * 1e3
    result.timings_ms["encode"] = (t_encode - t_segment) * 1e3
    result.timings_ms["total"] = (t_encode - t0) * 1e3
    return FrameOutputs(cloud=cloud, instances=instances, markers=markers, result=result)
