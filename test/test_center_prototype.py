"""Center prototypes: a center is compared with the points by the mean embedding of its like
neighbours, not by its own single (noisy) embedding."""
import numpy as np
import pytest

from fpcc_ros.clustering import center_prototypes
from fpcc_ros.model_card import ModelCard
from fpcc_ros.pipeline import ConfigError, Pipeline, PipelineConfig

R = 0.1


def test_prototype_is_the_mean_of_near_and_alike_points():
    xyz = np.array([[0, 0, 0],        # 0: the center
                    [0.03, 0, 0],     # 1: near, alike             -> in
                    [0, 0.04, 0],     # 2: near, alike             -> in
                    [0.02, 0, 0],     # 3: near, another part (embedding 2 away) -> out
                    [0.5, 0, 0]],     # 4: alike but beyond the radius           -> out
                   float)
    emb = np.array([[0.0, 0.0], [0.3, 0.0], [0.0, 0.3], [2.0, 0.0], [0.1, 0.1]])
    got = center_prototypes(xyz, emb, np.array([0, 3]), radius=0.06)
    np.testing.assert_allclose(got[0], [0.1, 0.1], atol=1e-6)   # mean of rows 0, 1, 2
    np.testing.assert_allclose(got[1], [2.0, 0.0], atol=1e-6)   # row 3 has no like neighbour
    np.testing.assert_allclose(center_prototypes(xyz, emb, np.array([0, 3]), radius=0.0),
                               emb[[0, 3]])


class NoisyCenterOracle:
    """Two flat parts 0.3 m apart, one score peak each. Every point of part i has embedding
    2·e_i plus a little noise, but the peak point's own embedding is 0.4 off: the paper's rule
    compares the points with that outlier."""

    def __init__(self, xyz: np.ndarray):
        self.card = ModelCard(name="oracle", k=8, part_radius=R, block_size=4096)
        self.origin = xyz.min(axis=0)

    def run(self, features: np.ndarray, knn: np.ndarray, global_stride: int = 1):
        xyz = features[0, :, :3].astype(np.float64) * R + self.origin
        part = (xyz[:, 0] > 0.2).astype(int)
        center_x = np.where(part == 1, 0.35, 0.05)
        dist = np.hypot(xyz[:, 0] - center_x, xyz[:, 1] - 0.05)
        score = np.clip(1 - (dist / R) ** 2, 0, 1)
        rng = np.random.default_rng(0)
        emb = np.zeros((len(xyz), 8))
        emb[np.arange(len(xyz)), part] = 2.0
        emb += rng.normal(0, 0.02, emb.shape)
        for i in (0, 1):
            peak = np.flatnonzero(part == i)[np.argmax(score[part == i])]
            emb[peak, 5] += 0.4
        return emb.astype(np.float32)[None], score.astype(np.float32)[None]


def flat_parts() -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.arange(21) * 0.005, np.arange(21) * 0.005, indexing="ij")
    square = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], 1)
    xyz = np.concatenate([square, square + [0.3, 0, 0]])
    return xyz, np.repeat([1, 2], x.size)


@pytest.mark.parametrize("prototype", [0.0, 0.5])
def test_prototype_recovers_the_parts_an_outlying_center_embedding_loses(prototype):
    xyz, truth = flat_parts()
    cfg = PipelineConfig(part_radius=R, voxel_size=0.0, remove_floor=False, min_points=10,
                         score_threshold=0.5, feature_gate=0.3, center_prototype=prototype)
    labels = Pipeline(NoisyCenterOracle(xyz), cfg).segment(xyz).labels
    covered = (labels > 0).mean()
    if prototype == 0:
        assert covered < 0.01          # every point is ~0.4 from its center's embedding
    else:
        assert covered > 0.6           # the points within d_max of a center
        for part in (1, 2):            # one instance per part, never across parts
            got = np.unique(labels[(truth == part) & (labels > 0)])
            assert len(got) == 1 and (truth[labels == got[0]] == part).all()


def test_center_prototype_range_is_checked():
    with pytest.raises(ConfigError, match="center_prototype"):
        PipelineConfig(part_radius=R).replace(center_prototype=3.0)


def test_chunked_prototypes_match_the_dense_definition(monkeypatch):
    import fpcc_ros.clustering as clustering

    monkeypatch.setattr(clustering, "ROW_CHUNK", 64)   # many chunks, centers across them
    xyz, emb, centers = clustered_parts(seed=3, parts=5, points=1000, noise=0.12)
    got = center_prototypes(xyz, emb, centers, radius=0.08)
    for row, c in zip(got, centers):
        np.testing.assert_allclose(row, dense_prototype(xyz, emb, c, np.arange(1000)), atol=1e-5)


def clustered_parts(seed: int, parts: int, points: int, noise: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points in ``parts`` tight 3D clusters with one embedding direction each, and the first
    row of each part as its center."""
    rng = np.random.default_rng(seed)
    owner = rng.integers(0, parts, points)
    xyz = rng.uniform(0, 1, (parts, 3))[owner] + rng.normal(0, 0.03, (points, 3))
    emb = rng.normal(0, 2, (parts, 16))[owner] + rng.normal(0, noise, (points, 16))
    return xyz, emb, np.array([np.flatnonzero(owner == i)[0] for i in range(parts)])


def dense_prototype(xyz: np.ndarray, emb: np.ndarray, center: int, rows: np.ndarray,
                    radius: float = 0.08) -> np.ndarray:
    """The definition, over ``rows``: the mean embedding of those within ``radius`` of the
    center in 3D and within 0.5 of its embedding."""
    take = rows[(np.linalg.norm(xyz[rows] - xyz[center], axis=1) <= radius)
                & (np.linalg.norm(emb[rows] - emb[center], axis=1) <= 0.5)]
    assert len(take) > 5
    return emb[take].mean(axis=0)


def test_large_passes_average_a_uniform_sample():
    """Beyond max_rows the mean runs over every stride-th row (the dense definition on that
    sample), and it stays close to the mean over all rows."""
    xyz, emb, centers = clustered_parts(seed=5, parts=4, points=4000, noise=0.08)
    full = center_prototypes(xyz, emb, centers, radius=0.08)
    got = center_prototypes(xyz, emb, centers, radius=0.08, max_rows=1000)   # stride 4
    for row, c in zip(got, centers):
        np.testing.assert_allclose(row, dense_prototype(xyz, emb, c, np.arange(0, 4000, 4)),
                                   atol=1e-5)
    assert np.abs(got - full).max() < 0.1 and not np.allclose(got, full)


def test_a_center_with_no_like_row_in_the_sample_keeps_its_own_embedding():
    xyz = np.zeros((10, 3))
    emb = np.zeros((10, 4))
    emb[1] = [3.0, 0, 0, 0]     # row 1 is a center unlike every sampled row (0, 2, 4, ...)
    got = center_prototypes(xyz, emb, np.array([1, 2]), radius=0.1, max_rows=5)
    np.testing.assert_allclose(got[0], emb[1])
    np.testing.assert_allclose(got[1], 0.0)
