"""PointCloud2 <-> numpy, instance messages, rosbag2 MCAP read/write and scene file formats.

Submodules import only numpy at load time; rclpy and rosbags are imported on first use, so the
pure-numpy pipeline and the bag tools can be used without a ROS environment and vice versa.
"""
from .msg_types import RCLPY, ROSBAGS, MessageTypes, msgtype_of, stamp_ns, types_for
from .palette import instance_color, label_colors, packed_rgb
from .point_cloud2 import (
    CloudFormatError,
    create_cloud,
    create_segmented_cloud,
    dtype_from_fields,
    read_points,
    read_xyz,
    validate_cloud,
)
from .instances import create_instance_markers, create_pose_array

__all__ = [
    "RCLPY", "ROSBAGS", "MessageTypes", "msgtype_of", "stamp_ns", "types_for",
    "instance_color", "label_colors", "packed_rgb",
    "CloudFormatError", "create_cloud", "create_segmented_cloud", "dtype_from_fields",
    "read_points", "read_xyz", "validate_cloud",
    "create_instance_markers", "create_pose_array",
]
