"""Center merging: a small screening radius keeps parallel elongated parts apart, and centers
that one network pass embeds alike (one part) are merged back into one instance."""
import numpy as np
import pytest

from fpcc_ros.clustering import close_center_pairs, merge_centers
from fpcc_ros.model_card import ModelCard
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig

R = 0.1           # part radius: rods 0.2 m long
GAP = 0.05        # rods side by side, axes 5 cm apart (half a part radius)


def rods(count: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Top faces of parallel rods along x (41 x 5 points at 5 mm), and their labels 1..count."""
    x, y = np.meshgrid(np.arange(41) * 0.005, np.arange(5) * 0.005, indexing="ij")
    xyz, labels = [], []
    for i in range(count):
        xyz.append(np.stack([x.ravel(), y.ravel() + i * GAP, np.full(x.size, 1.0 + 0.001 * i)], 1))
        labels.append(np.full(x.size, i + 1))
    return np.concatenate(xyz), np.concatenate(labels)


class RodOracle:
    """Stands in for FPCC-Net on :func:`rods` scenes (one block, no floor): a broad center score
    with two peaks per rod, 12 cm apart (as an undertrained network gives an elongated part), and
    one embedding per rod, 2.8 apart (or, with ``spacing``, rod i at i * spacing along one
    axis: neighbouring rods alike, rods two apart not)."""

    def __init__(self, xyz: np.ndarray, labels: np.ndarray, spacing: float | None = None):
        self.card = ModelCard(name="oracle", k=8, part_radius=R, block_size=4096)
        self.origin, self.labels, self.spacing = xyz.min(axis=0), labels, spacing

    def run(self, features: np.ndarray, knn: np.ndarray, global_stride: int = 1):
        xyz = features[0, :, :3].astype(np.float64) * R + self.origin
        along = xyz[:, 0] - 0.1                               # rod centers at x = 0.1
        peak = np.minimum(np.abs(along - 0.06), np.abs(along + 0.06))
        score = np.clip(1 - (peak / 0.03) ** 2, 0, 1) * 0.9
        rod = np.rint((xyz[:, 1] - self.origin[1] - 0.01) / GAP).astype(int)
        embedding = np.zeros((len(xyz), 8), np.float32)
        if self.spacing is None:
            embedding[np.arange(len(xyz)), rod] = 2.0
        else:
            embedding[:, 0] = rod * self.spacing
        return embedding[None], score.astype(np.float32)[None]


def segment(center_merge: float, screening_factor: float, count: int = 3,
            spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    xyz, labels = rods(count)
    cfg = PipelineConfig(part_radius=R, voxel_size=0.0, remove_floor=False, min_points=10,
                         score_threshold=0.5, screening_factor=screening_factor,
                         center_merge=center_merge, block_size=4096)
    return Pipeline(RodOracle(xyz, labels, spacing), cfg).segment(xyz).labels, labels


def instances_per_rod(pred: np.ndarray, truth: np.ndarray) -> list[int]:
    return [len(np.unique(pred[(truth == t) & (pred > 0)])) for t in np.unique(truth)]


def test_small_screening_radius_alone_splits_each_rod_in_two():
    pred, truth = segment(center_merge=0.0, screening_factor=0.3)
    assert instances_per_rod(pred, truth) == [2, 2, 2]


def test_paper_screening_radius_loses_neighbouring_rods():
    pred, truth = segment(center_merge=0.0, screening_factor=1.0)
    # the 10 cm sphere around the first rod's centers swallows the rod 5 cm beside it
    assert (pred[truth == 2] == 0).all()


def test_merging_gives_one_instance_per_rod():
    pred, truth = segment(center_merge=0.5, screening_factor=0.3)
    assert instances_per_rod(pred, truth) == [1, 1, 1]
    # and never one instance across two rods
    for label in np.unique(pred[pred > 0]):
        assert len(np.unique(truth[pred == label])) == 1


def test_close_center_pairs_needs_both_3d_and_embedding_closeness():
    xyz = np.array([[0, 0, 0], [0.15, 0, 0], [0.4, 0, 0], [0, 0.02, 0]], float)
    emb = np.array([[0, 0], [0.1, 0], [0, 0], [3, 0]], float)
    pairs = close_center_pairs(xyz, emb, d_max=0.1, max_distance=0.5)
    # 0-1: within 2 d_max and alike; 0-2, 1-2 alike but 2 d_max or more apart; 0-3 near, unlike
    assert pairs.tolist() == [[0, 1]]


def test_merge_centers_joins_groups_only_when_all_their_centers_are_paired():
    # 0-1-2 a chain (0 and 2 not a pair): the first pair wins, 2 stays alone
    assert merge_centers(3, np.array([[0, 1], [1, 2]])).tolist() == [0, 0, 2]
    assert merge_centers(3, np.array([[1, 2], [0, 1]])).tolist() == [0, 1, 1]
    # every center paired with every other: one group, named by its lowest rank
    assert merge_centers(4, np.array([[2, 3], [1, 3], [1, 2]])).tolist() == [0, 1, 1, 1]
    assert merge_centers(6, np.array([[1, 4], [2, 3]])).tolist() == [0, 1, 2, 2, 1, 5]
    assert merge_centers(3, np.zeros((0, 2), int)).tolist() == [0, 1, 2]


def test_close_center_pairs_come_most_alike_first():
    xyz = np.zeros((3, 3))
    emb = np.array([[0.0], [0.4], [0.3]])
    pairs = close_center_pairs(xyz, emb, d_max=0.1, max_distance=0.5)
    assert pairs.tolist() == [[1, 2], [0, 2], [0, 1]]


def test_merging_does_not_chain_a_row_of_alike_neighbours_into_one_instance():
    # rod i embedded at 0.4 i: each rod is alike its neighbours (0.4 < 0.5) but not the rod
    # two over (0.8); the rods' two centers each are pairwise within 2 d_max
    pred, truth = segment(center_merge=0.5, screening_factor=0.3, count=3, spacing=0.4)
    rods_per_instance = [len(np.unique(truth[pred == label])) for label in np.unique(pred[pred > 0])]
    assert max(rods_per_instance) <= 2
    assert instances_per_rod(pred, truth) == [1, 1, 1]


def test_center_merge_range_is_checked():
    with pytest.raises(ConfigError, match="center_merge"):
        PipelineConfig(part_radius=R).replace(center_merge=-1.0)
