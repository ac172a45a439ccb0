"""Instance centroids -> geometry_msgs/PoseArray and visualization_msgs/MarkerArray.

``instances`` is what a pose estimator consumes (poses[i] = centroid of label i+1, identity
orientation); ``instance_markers`` is for people in RViz/Foxglove: a DELETEALL first so the
markers of a frame with fewer instances do not linger, then a sphere and a text per instance in
the label's palette colour. Both carry the input cloud's header (stamp and frame).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .msg_types import RCLPY, MessageTypes
from .palette import instance_color

__all__ = ["create_pose_array", "create_instance_markers", "sphere_id", "text_id",
           "MARKER_SPHERE", "MARKER_TEXT_VIEW_FACING", "MARKER_ADD", "MARKER_DELETEALL"]

# visualization_msgs/Marker constants (same in both flavours; spelled out so no class is needed).
MARKER_SPHERE = 2
MARKER_TEXT_VIEW_FACING = 9
MARKER_ADD = 0
MARKER_DELETEALL = 3


def sphere_id(label: int) -> int:
    """Marker id of the sphere of ``label``: stable across frames, so RViz updates in place."""
    return 2 * int(label)


def text_id(label: int) -> int:
    """Marker id of the text of ``label``."""
    return 2 * int(label) + 1


def _centroids(centroids: np.ndarray) -> np.ndarray:
    c = np.asarray(centroids, dtype=np.float64)
    if c.size == 0:
        return c.reshape(0, 3)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centroids must have shape (K, 3) (row i = label i+1), got {c.shape}")
    return c


def create_pose_array(header: Any, centroids: np.ndarray, types: MessageTypes = RCLPY) -> Any:
    """PoseArray with ``poses[i]`` at the centroid of label ``i+1``, identity orientation."""
    c = _centroids(centroids)
    return types.pose_array(header, [types.pose(tuple(p)) for p in c.tolist()])


def create_instance_markers(
    header: Any,
    centroids: np.ndarray,
    point_counts: Sequence[int] | np.ndarray,
    types: MessageTypes = RCLPY,
    ns: str = "fpcc",
    sphere_diameter: float = 0.02,
    text_height: float = 0.02,
) -> Any:
    """MarkerArray: DELETEALL, then per instance a SPHERE and a TEXT_VIEW_FACING "3 (1520 pts)".

    Label ``i+1`` is row ``i`` of ``centroids``; its sphere has id ``2*(i+1)`` and its text id
    ``2*(i+1)+1`` in namespace ``ns``. Colours are the palette's (as in the ``rgb`` field).
    Instances with a non-finite centroid get no markers (RViz rejects NaN poses).
    """
    c = _centroids(centroids)
    counts = np.asarray(point_counts).reshape(-1)
    if len(counts) != len(c):
        raise ValueError(f"point_counts has {len(counts)} entries but centroids has {len(c)} rows")
    hdr = types.header_from(header)
    markers = [types.marker(hdr, ns=ns, id=0, action=MARKER_DELETEALL)]
    finite = np.isfinite(c).all(axis=1)
    for i, (pos, count, ok) in enumerate(zip(c.tolist(), counts.tolist(), finite.tolist())):
        if not ok:
            continue
        label = i + 1
        color = types.color_rgba(*instance_color(label), 1.0)
        markers.append(types.marker(
            hdr, ns=ns, id=sphere_id(label), type=MARKER_SPHERE, action=MARKER_ADD,
            pose=types.pose(pos), scale=types.vector3(sphere_diameter, sphere_diameter, sphere_diameter),
            color=color,
        ))
        markers.append(types.marker(
            hdr, ns=ns, id=text_id(label), type=MARKER_TEXT_VIEW_FACING, action=MARKER_ADD,
            pose=types.pose(pos), scale=types.vector3(0.0, 0.0, text_height),
            color=types.color_rgba(*instance_color(label), 1.0), text=f"{label} ({int(count)} pts)",
        ))
    return types.marker_array(markers)
