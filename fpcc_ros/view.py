"""Which way the camera looks, in the cloud's frame, and the turn that shows the network the
cloud as its camera saw it.

FPCC-Net is trained on clouds in the camera's optical frame (REP-103: z forward, into the bin).
Its inputs are block coordinates, so a cloud whose frame has another orientation reaches it upside
down: a z-up world or robot-base frame (the camera above the bin looks along -z) shows it the
parts' undersides as dents. That costs most of the accuracy (a third-party gear-shaft scene in a
z-up frame: 2 of 19 parts found as given, 5 turned into the camera's view), so the pipeline turns
the network's inputs (only those: labels, centroids and the ROI stay in the cloud's frame).

``auto`` tells the two common cases apart from the points alone. A camera frame has the
viewpoint at its origin: every point lies in front of it (z > 0) inside a view cone. A z-up world
or robot-base frame puts the floor near z = 0 or the bin off to the side of the origin, so some
points fall outside any cone in front of it; such a cloud is taken as seen from above (-z, REP-103
z up). A camera frame whose name says nothing ("PhoXi3Dscanner_sensor", "camera") is recognised
by its geometry, not its name. A cloud in a z-up frame that sits entirely inside a cone above the
origin (a bin 2 m up, right over it) cannot be told from a camera's view: set ``view_axis``.
(For organized clouds a pinhole test was tried: x/z linear along the image rows. A flat floor seen
from a transformed frame passes it too, and real lenses' distortion bends it, so it was dropped.)
"""
from __future__ import annotations

import numpy as np

VIEW_AXES = ("auto", "+z", "-z", "+x", "-x", "+y", "-y")
# The rotation taking each viewing direction onto +z (det +1; the turn about the viewing axis
# is free: training augments it).
_TO_CAMERA = {
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "+x": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),
    "+y": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "-y": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}
CONE_SLOPE = 2.0       # |x| / z and |y| / z up to this (a 127 degree field of view) in a camera frame
SAMPLE = 4096          # points the test looks at


def to_camera(xyz: np.ndarray, view_axis: str) -> np.ndarray:
    """``xyz`` turned so that ``view_axis`` (not ``auto``) points along +z."""
    if view_axis == "+z":
        return xyz
    return xyz @ _TO_CAMERA[view_axis].T


def depth_axis(view_axis: str) -> tuple[int, float]:
    """The column of the cloud and the sign that give depth (distance along the view) for
    ``view_axis`` (not ``auto``): ``-z`` -> (2, -1.0)."""
    return "xyz".index(view_axis[1]), (1.0 if view_axis[0] == "+" else -1.0)


def detect_view_axis(xyz: np.ndarray) -> str:
    """``+z`` when the finite points of ``xyz`` (N, 3) could all be seen from the frame's
    origin looking along +z (in front of it, inside a 127 degree cone), else ``-z`` (see the
    module docstring)."""
    p = np.asarray(xyz[::max(1, len(xyz) // SAMPLE)], dtype=np.float64)   # a sample first:
    p = p[np.isfinite(p).all(axis=1)]   # the pipeline's points are finite already
    if len(p) < 3:
        return "+z"
    z = p[:, 2]
    if (z <= 0).any():
        return "-z"
    in_cone = (np.abs(p[:, :2]) <= CONE_SLOPE * z[:, None]).all()
    return "+z" if in_cone else "-z"
