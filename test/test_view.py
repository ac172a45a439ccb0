"""The camera's viewing direction: detected from the points, and the turn the network sees."""
import numpy as np
import pytest

from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig
from fpcc_ros.view import VIEW_AXES, detect_view_axis, to_camera

from cloud_factory import scene_xyz
from conftest import TEST_DATA

AXIS_VECTORS = {"+x": [1, 0, 0], "-x": [-1, 0, 0], "+y": [0, 1, 0], "-y": [0, -1, 0],
                "+z": [0, 0, 1], "-z": [0, 0, -1]}


def z_up(camera_xyz: np.ndarray, height: float) -> np.ndarray:
    """A camera-frame cloud as a z-up world frame sees it: the camera ``height`` above the
    floor at z = 0, looking straight down (camera x = world x, camera y = world -y)."""
    x, y, z = np.moveaxis(camera_xyz.astype(np.float64), -1, 0)
    return np.stack([x, -y, height - z], axis=-1)


@pytest.mark.parametrize("axis", [a for a in VIEW_AXES if a != "auto"])
def test_each_axis_turns_onto_plus_z_by_a_proper_rotation(axis):
    v = np.array([AXIS_VECTORS[axis]], dtype=np.float64)
    np.testing.assert_allclose(to_camera(v, axis), [[0, 0, 1]], atol=1e-12)
    turn = to_camera(np.eye(3), axis).T          # the matrix itself: columns are the images
    np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(turn) == pytest.approx(1.0)   # a turn, never a mirror image


def test_a_camera_frame_cloud_is_recognised():
    cam = scene_xyz(48, 64, seed=1)
    assert detect_view_axis(cam.reshape(-1, 3)) == "+z"


@pytest.mark.parametrize("floor_height", [0.0, 0.3])
def test_a_z_up_world_frame_cloud_is_seen_from_above(floor_height):
    """The floor at z = 0 (points at z <= 0), or higher with the bin beside the origin (points
    outside the cone): either way not a camera's view."""
    world = z_up(scene_xyz(48, 64, seed=2), height=0.8 + floor_height).reshape(-1, 3)
    world[:, 0] += 1.0 if floor_height else 0.0    # a bin 1 m beside the robot base
    assert detect_view_axis(world) == "-z"


def test_a_z_up_cloud_in_front_of_the_origin_is_the_documented_limit():
    """A bin 2 m up, right over the origin: inside the cone, taken as a camera's view."""
    world = z_up(scene_xyz(48, 64, seed=3), height=2.8).reshape(-1, 3)
    assert detect_view_axis(world) == "+z"
    assert detect_view_axis(world * [1, 1, -1]) == "-z"   # the same cloud below the origin


def test_no_points_or_garbage_give_an_answer_not_an_error():
    assert detect_view_axis(np.full((10, 3), np.nan)) == "+z"
    with np.errstate(all="raise"):   # no silent overflow either
        assert detect_view_axis(np.array([[1e30, 0, 1e-30], [0, 0, 1], [1, 1, 1]])) == "-z"


def test_the_pipeline_shows_the_network_the_same_view_from_either_frame():
    model = FpccModel(TEST_DATA / "tiny_fpcc.onnx", threads=1)
    cam = scene_xyz(96, 128, seed=4, spheres=10)
    world = z_up(cam, height=0.8).astype(np.float32)
    cfg = PipelineConfig.from_card(model.card, part_radius=0.04, min_points=1,
                                   score_threshold=0.3)
    from_cam = Pipeline(model, cfg).segment(cam.reshape(-1, 3))
    from_world = Pipeline(model, cfg).segment(world.reshape(-1, 3))
    assert (from_cam.view_axis, from_world.view_axis) == ("+z", "-z")
    assert from_cam.num_instances > 1
    # the same network inputs up to a shift (features are block-relative): the same labels,
    # bar float rounding at a few boundary points
    assert from_world.num_instances == from_cam.num_instances
    assert (from_world.labels == from_cam.labels).mean() > 0.99
    # the centroids stay in each cloud's own frame
    np.testing.assert_allclose(from_world.centroids, z_up(from_cam.centroids, 0.8), atol=1e-4)
    # told the wrong way round, the network sees another scene
    wrong = Pipeline(model, cfg.replace(view_axis="+z")).segment(world.reshape(-1, 3))
    assert wrong.view_axis == "+z"
    assert not np.array_equal(wrong.center_score, from_cam.center_score)


def test_an_unknown_view_axis_is_refused_with_the_choices():
    with pytest.raises(ConfigError, match=r"view_axis='down' is invalid.*\+z.*-z"):
        PipelineConfig(part_radius=0.05).replace(view_axis="down")
