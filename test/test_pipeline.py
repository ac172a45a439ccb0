"""Pipeline contract with the tiny (untrained) test model: what must hold whatever it predicts."""
import numpy as np
import pytest

from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig

from conftest import TEST_DATA


@pytest.fixture(scope="module")
def model():
    return FpccModel(TEST_DATA / "tiny_fpcc.onnx", threads=1)


def _scene(seed=0, n=20_000):
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), np.full(n, 1.0) + rng.normal(0, 5e-4, n)]
    blobs = np.concatenate([c + rng.normal(0, 0.02, (2000, 3)) for c in
                            ([0.1, 0.1, 0.95], [-0.1, 0.0, 0.95], [0.0, -0.15, 0.95])])
    xyz = np.vstack([floor, blobs]).astype(np.float32)
    xyz[::50] = np.nan
    return xyz


def test_labels_are_index_aligned_and_only_on_finite_points(model):
    xyz = _scene()
    result = Pipeline(model, PipelineConfig.from_card(model.card, part_radius=0.05,
                                                      min_points=1)).segment(xyz)
    assert result.labels.shape == (len(xyz),) and result.labels.dtype == np.uint32
    assert not result.labels[~np.isfinite(xyz).all(axis=1)].any()
    distinct = np.unique(result.labels[result.labels > 0])
    assert distinct.tolist() == list(range(1, result.num_instances + 1))
    for i, count in enumerate(result.point_counts):
        assert (result.labels == i + 1).sum() == count
        np.testing.assert_allclose(result.centroids[i],
                                   xyz[result.labels == i + 1].astype(np.float64).mean(0), atol=1e-6)


def test_half_open_roi_crops_from_one_side(model):
    xyz = _scene(1)
    cfg = PipelineConfig.from_card(model.card, part_radius=0.05, min_points=1,
                                   roi_min=[0.0, -1.0, 0.0])
    result = Pipeline(model, cfg).segment(xyz)
    assert not result.labels[xyz[:, 0] < 0].any()
    assert result.num_valid == int((np.isfinite(xyz).all(1) & (xyz[:, 0] >= 0)).sum())


def test_roi_corners_must_be_ordered():
    with pytest.raises(ConfigError, match="must be below roi_max"):
        PipelineConfig(part_radius=0.05).replace(roi_min=[1, 0, 0], roi_max=[0, 1, 1])


@pytest.mark.parametrize("key, value", [("part_radius", -0.1), ("score_threshold", 1.5),
                                        ("voxel_size", -0.5), ("min_points", -1),
                                        ("global_stride", 0), ("global_stride", 17),
                                        ("global_stride", 2.0), ("global_stride", True)])
def test_out_of_range_settings_are_refused_and_named(key, value):
    with pytest.raises(ConfigError, match=key):
        PipelineConfig(part_radius=0.05).replace(**{key: value})


def test_empty_and_all_nan_clouds_give_no_instances(model):
    pipe = Pipeline(model, PipelineConfig.from_card(model.card, part_radius=0.05))
    for xyz in (np.zeros((0, 3), np.float32), np.full((100, 3), np.nan, np.float32)):
        result = pipe.segment(xyz)
        assert result.num_instances == 0 and not result.labels.any()


def test_absurd_coordinates_are_treated_as_no_return(model):
    rng = np.random.default_rng(5)
    xyz = _scene(2)
    xyz[:100] = rng.uniform(-1, 1, (100, 3)) * 1e30
    result = Pipeline(model, PipelineConfig.from_card(model.card, part_radius=0.05,
                                                      min_points=1)).segment(xyz)
    assert not result.labels[:100].any()
    assert result.num_valid == int(np.isfinite(xyz[100:]).all(axis=1).sum())


def test_voxel_downsample_survives_kilometre_extents():
    from fpcc_ros.features import voxel_downsample
    xyz = np.array([[0.0, 0, 0], [0.001, 0, 0], [9000.0, 9000.0, 9000.0]])
    keep, inverse = voxel_downsample(xyz, 1e-4)
    assert len(keep) == 3 and sorted(inverse.tolist()) == [0, 1, 2]


def test_a_frame_runs_with_blas_on_the_calling_thread_and_restores_it(model):
    """segment pins BLAS for the whole frame (its spinning pool would take the core the kNN
    queries and onnxruntime need) and leaves the process's BLAS threads as they were."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    controller = threadpoolctl.ThreadpoolController()
    blas = controller.select(user_api="blas")
    if not blas.lib_controllers:
        pytest.skip("numpy's BLAS is not visible to threadpoolctl")

    def blas_threads() -> list[int]:
        return [lib.num_threads for lib in threadpoolctl.ThreadpoolController()
                .select(user_api="blas").lib_controllers]

    pipe = Pipeline(model, PipelineConfig.from_card(model.card, part_radius=0.05, min_points=1))
    seen: list[list[int]] = []
    run = pipe.model.run

    def spy(*args, **kwargs):
        seen.append(blas_threads())
        return run(*args, **kwargs)

    with blas.limit(limits=2):
        pipe.model.run = spy
        try:
            labels = pipe.segment(_scene()).labels
        finally:
            del pipe.model.run
        assert seen and all(threads == [1] * len(threads) for threads in seen)
        assert blas_threads() == [2] * len(seen[0])
    # the same labels as the steps run without the pin
    np.testing.assert_array_equal(labels, pipe._segment(_scene()).labels)


def test_a_global_stride_needs_a_model_that_takes_it(model, tmp_path):
    """The tiny model's graph has no global_stride input: a stride other than 1 is refused at
    set-up with the fix named; the same net through scripts/optimize_onnx.py segments with it,
    and at stride 1 exactly as the plain graph does."""
    from fpcc_ros.graph_rewrite import optimize_file

    config = PipelineConfig.from_card(model.card, part_radius=0.05, min_points=1)
    with pytest.raises(ConfigError, match="global_stride=2 .*optimize_onnx"):
        Pipeline(model, config.replace(global_stride=2))
    optimize_file(TEST_DATA / "tiny_fpcc.onnx", tmp_path / "fast.onnx")
    (tmp_path / "fast.json").write_text((TEST_DATA / "tiny_fpcc.json").read_text())
    fast = FpccModel(tmp_path / "fast.onnx", threads=1)
    xyz = _scene(3)
    plain = Pipeline(model, config).segment(xyz)
    exact = Pipeline(fast, config).segment(xyz)
    np.testing.assert_array_equal(exact.labels, plain.labels)
    strided = Pipeline(fast, config.replace(global_stride=4)).segment(xyz)
    assert strided.labels.shape == plain.labels.shape
    assert not np.array_equal(strided.center_score, plain.center_score)   # the stride is fed
