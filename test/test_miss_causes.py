"""fpcc eval's error breakdown on hand-built labels whose every cause is known."""
from pathlib import Path

import numpy as np

import fpcc_ros.pipeline as pipeline_module
from fpcc_ros.evaluation import evaluate
from fpcc_ros.miss_causes import describe, error_causes
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import Pipeline, PipelineConfig, SegmentationResult

from conftest import TEST_DATA
from test_evaluation import FLOOR, ROW, write_scene

THETA = 0.5


def _scene():
    """Ten points per visible part (the visible limit is 5 here), laid out block by block:
    (gt, pred, score, on a kept center) per point."""
    rows = []

    def block(gt, preds, score=0.9, center=True):
        for i, p in enumerate(preds):
            rows.append((gt, p, score, center and i == 0))

    block(1, [1] * 10)                                 # matched
    block(2, [0] * 10, score=0.2, center=False)        # no score above θ
    block(3, [0] * 10, center=False)                   # candidates, no kept center
    block(4, [4] * 3 + [0] * 7)                        # centered, mostly unlabelled
    for part in (5, 6, 7):                             # one instance over three parts
        block(part, [5] * 10)
    block(8, [81] * 4 + [82] * 3 + [83] * 3)           # three pieces, none with half
    block(9, [9] * 2)                                  # 2 points: too small to count
    rows += [(0, 10, 0.0, False)] * 15 + [(0, 0, 0.0, False)] * 5   # floor, part of it labelled
    gt, pred, score, center = (np.array(c) for c in zip(*rows))
    return gt, pred, score.astype(np.float32), np.flatnonzero(center)


def test_each_miss_and_extra_is_put_down_to_its_stage():
    gt, pred, score, centers = _scene()
    causes = error_causes(pred, gt, score, centers, THETA, min_visible=5)
    assert causes["missed"] == {"no_center": 1, "suppressed": 1, "unlabelled": 1, "merged": 3,
                                "split": 1}
    # pred 4 and the three pieces of part 8; pred 5 over parts 5-7; pred 10 on the floor;
    # pred 9 lies only on a part too small to count, so it is not scored at all
    assert causes["extra"] == {"piece": 4, "spans_parts": 1, "background": 1}


def test_without_center_points_nothing_is_called_suppressed():
    gt, pred, score, _ = _scene()
    causes = error_causes(pred, gt, score, None, THETA, min_visible=5)
    assert causes["missed"]["suppressed"] == 0
    assert causes["missed"]["unlabelled"] == 2       # part 3 falls through to its labels


def test_a_perfect_prediction_has_no_errors_and_the_summary_says_so():
    gt = np.repeat([1, 2, 3, 0], 10)
    causes = error_causes(gt, gt, np.ones(len(gt), np.float32), np.array([0, 10, 20]), THETA, 5)
    assert sum(causes["missed"].values()) == sum(causes["extra"].values()) == 0
    missed, extra = describe(causes)
    assert missed.startswith("missed visible parts (0)")
    assert extra.startswith("extra instances (0)")


class MergingPipeline:
    """Predicts a scene's three parts as one instance (two of three would still match: IoU 0.5)."""

    def __init__(self):
        self.config = PipelineConfig(part_radius=0.05)

    def segment(self, xyz, image_shape=None):
        labels = self.truth.copy()
        labels[labels > 1] = 1
        return SegmentationResult(labels=labels.astype(np.uint32),
                                  center_score=np.ones(len(xyz), np.float32),
                                  centroids=np.zeros((1, 3)), point_counts=np.ones(1, np.int64),
                                  num_valid=len(xyz), num_network_points=len(xyz),
                                  center_points=np.flatnonzero(np.diff(self.truth, prepend=0)))


def test_eval_report_sums_the_causes_over_scenes(tmp_path):
    fake = MergingPipeline()
    for name in ("a.npz", "b.npz"):
        fake.truth = write_scene(tmp_path / name, ROW, extra=FLOOR, organized=(48, 64))
    report = evaluate([tmp_path / "a.npz", tmp_path / "b.npz"], fake, baseline=False)
    causes = report.error_causes()
    assert causes["missed"]["merged"] == 6            # three parts in each of two scenes
    assert causes["extra"]["spans_parts"] == 2
    assert "missed visible parts (6)" in report.summary()
    assert report.to_json()["error_causes"] == causes
    paper_only = evaluate([tmp_path / "a.npz"], fake, baseline=False, protocols=["paper"])
    assert paper_only.error_causes() is None


def test_center_points_are_the_points_nms_kept(monkeypatch):
    model = FpccModel(TEST_DATA / "tiny_fpcc.onnx", threads=1)
    kept = []
    real_nms = pipeline_module.nms_centers

    def spy(xyz, score, threshold, radius):
        centers = real_nms(xyz, score, threshold, radius)
        kept.append(xyz[centers])
        return centers

    monkeypatch.setattr(pipeline_module, "nms_centers", spy)
    rng = np.random.default_rng(3)
    xyz = np.concatenate([c + rng.normal(0, 0.01, (3000, 3)) for c in
                          ([0.1, 0.1, 0.95], [-0.1, 0.0, 0.95])]).astype(np.float32)
    cfg = PipelineConfig.from_card(model.card, part_radius=0.05, score_threshold=0.0,
                                   voxel_size=0.01)
    result = Pipeline(model, cfg).segment(xyz)
    assert len(result.center_points) == len(kept[0]) > 0
    assert (result.center_score[result.center_points] >= 0.0).all()
    # each center's point lies in that center's voxel (a 1 cm cell around it)
    gap = np.abs(xyz[result.center_points][:, None] - kept[0][None]).max(axis=2).min(axis=1)
    assert (gap <= 0.01 + 1e-6).all()
