"""Majority vote over the network's neighbourhood graph after clustering."""
import numpy as np
import pytest

from fpcc_ros.clustering import majority_labels
from fpcc_ros.model_card import ModelCard
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig


def test_majority_takes_the_commonest_neighbour_label_and_keeps_its_own_on_ties():
    labels = np.array([1, 1, 2, 2, 0, 3])
    rows = np.array([0, 2, 4, 5])
    neighbours = np.array([[0, 2, 3, 4],    # 2 x label 2, one 1, one 0   -> 2
                           [2, 0, 1, 4],    # 2 x label 1, one 2, one 0   -> 1
                           [4, 5, 0, 2],    # one each of 0, 3, 1, 2: tie -> own (0)
                           [5, 5, 2, 2]])   # tie 3/2, own 3 among them   -> 3
    assert majority_labels(labels, rows, neighbours).tolist() == [2, 1, 0, 3]
    assert majority_labels(labels, rows[:0], neighbours[:0]).tolist() == []


class StrayPointOracle:
    """One flat part with one score peak; every point embeds alike except a few scattered ones
    whose embeddings sit 2 away (as a poorly trained network leaves some): the gate drops them."""

    STRAY = np.arange(7, 400, 37)

    def __init__(self):
        self.card = ModelCard(name="oracle", k=8, part_radius=0.1, block_size=4096)

    def run(self, features: np.ndarray, knn: np.ndarray, global_stride: int = 1):
        xyz = features[0, :, :3].astype(np.float64) * 0.1
        dist = np.linalg.norm(xyz[:, :2] - xyz[:, :2].mean(axis=0), axis=1)
        score = np.clip(1 - (dist / 0.1) ** 2, 0, 1)
        emb = np.zeros((len(xyz), 4), np.float32)
        emb[self.STRAY, 1] = 2.0
        return emb[None], score.astype(np.float32)[None]


@pytest.mark.parametrize("passes", [0, 1])
def test_smoothing_gives_gated_out_points_inside_a_part_its_label(passes):
    x, y = np.meshgrid(np.arange(20) * 0.005, np.arange(20) * 0.005, indexing="ij")
    xyz = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], 1)
    cfg = PipelineConfig(part_radius=0.1, voxel_size=0.0, remove_floor=False, min_points=10,
                         score_threshold=0.5, feature_gate=0.5, label_smoothing=passes)
    labels = Pipeline(StrayPointOracle(), cfg).segment(xyz).labels
    stray = StrayPointOracle.STRAY
    others = np.setdiff1d(np.arange(len(xyz)), stray)
    assert (labels[others] == 1).all()
    if passes == 0:
        assert (labels[stray] == 0).all()
    else:
        assert (labels[stray] == 1).all()


def test_label_smoothing_range_is_checked():
    with pytest.raises(ConfigError, match="label_smoothing"):
        PipelineConfig(part_radius=0.1).replace(label_smoothing=-1)
