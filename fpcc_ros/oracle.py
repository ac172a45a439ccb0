"""The clustering's ceiling: ground truth standing in for the network (`fpcc eval --oracle-embeddings`).

:class:`OraclePipeline` is the runtime pipeline with one change: each network pass returns,
instead of FPCC-Net's outputs, the scene's ground-truth center score and an embedding that is
a one-hot vector of the point's ground-truth instance (background: zero). Points of one part are
then 0 apart in feature space, of two parts sqrt(2), part and background 1: a perfectly trained
network under the loss's margins (eps1 0.5, eps2 1). Everything else (valid points, voxels,
floor, blocks, NMS at the card's θ and γ, gates, center merging, the clustering mode) runs as
in the node, so what the oracle scores is the best that clustering can do on those scenes, and a
change that lowers it is a regression of the clustering, not of a model.

With one head only (``heads``: ``center_score`` or ``embedding``) the network runs and ground
truth replaces that one of its two outputs: which head limits a model. On the IPA gear-shaft
piles the shipped network's own centers with ground-truth embeddings scored F1 0.661 against
0.663 for the full oracle and 0.581 for the network alone (4 piles, card settings): its
embeddings, not its centers, are what it lacks.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fpcc_ros.pipeline import Pipeline, _BlockRun, _StageClock

# the network's two outputs that ground truth can stand in for
ORACLE_HEADS = ("center_score", "embedding")


class OraclePipeline(Pipeline):
    """A :class:`Pipeline` over one scene whose network passes return ground truth.

    ``instance`` and ``center_score`` are flat over the scene's points (the rows that
    ``segment`` will be given). With both ``heads`` the model is used for its card only (k,
    block size), never run; with one, the network's other output is kept.
    """

    def __init__(self, pipeline: Pipeline, instance: np.ndarray, center_score: np.ndarray,
                 heads: tuple[str, ...] = ORACLE_HEADS):
        unknown = sorted(set(heads) - set(ORACLE_HEADS))
        if unknown or not heads:
            raise ValueError(f"oracle heads {list(heads)} are invalid: give one or both of "
                             f"{list(ORACLE_HEADS)}")
        super().__init__(pipeline.model, pipeline.config)
        self._heads = frozenset(heads)
        self._instance = np.asarray(instance, dtype=np.int64).reshape(-1)
        self._score = np.asarray(center_score, dtype=np.float64).reshape(-1)
        self._net_instance = np.zeros(0, np.int64)
        self._net_score = np.zeros(0, np.float32)

    def _network_points(self, xyz: np.ndarray, clock: _StageClock):
        out = super()._network_points(xyz, clock)
        valid_idx, inverse, net_xyz = out[0], out[1], out[4]
        if len(self._instance) != len(xyz):
            raise ValueError(f"oracle ground truth has {len(self._instance)} points but the "
                             f"cloud has {len(xyz)}; give the scene's own 'instance'")
        self._net_instance, self._net_score = representative_truth(
            inverse, self._instance[valid_idx], self._score[valid_idx], len(net_xyz))
        return out

    def _run_block(self, core: np.ndarray, ext: np.ndarray, feats: np.ndarray,
                   knn: np.ndarray) -> _BlockRun:
        network = None if self._heads == set(ORACLE_HEADS) else \
            super()._run_block(core, ext, feats, knn)
        if "embedding" in self._heads:
            dim = self.model.card.embedding_dim
            instance = self._net_instance[ext]
            embedding = np.zeros((len(ext), dim), np.float32)
            part = instance > 0
            embedding[np.flatnonzero(part), instance[part] % dim] = 1.0
        else:
            embedding = network.embedding
        score = self._net_score[core].astype(np.float32) if "center_score" in self._heads \
            else network.score
        return _BlockRun(core=core, ext=ext, embedding=embedding, score=score)


def representative_truth(inverse: np.ndarray, instance: np.ndarray, score: np.ndarray,
                         num_representatives: int) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel representative: the instance most of its input points carry (ties: the
    smaller id) and their mean center score."""
    ids, compact = np.unique(instance, return_inverse=True)
    votes = np.bincount(inverse * len(ids) + compact, minlength=num_representatives * len(ids))
    majority = ids[votes.reshape(num_representatives, len(ids)).argmax(axis=1)]
    counts = np.maximum(np.bincount(inverse, minlength=num_representatives), 1)
    mean = np.bincount(inverse, weights=score, minlength=num_representatives) / counts
    return majority.astype(np.int64), mean.astype(np.float32)


def scene_truth(path: Path, part_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A scene's flat ground-truth ``instance`` and ``center_score``. A scene without
    ``center_score`` (a text scene, or an NPZ without it) gets DESIGN's score around each
    instance's centroid of visible points instead of its geometric center."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            instance = z["instance"].reshape(-1).astype(np.int64)
            points = z["points"].reshape(-1, 3)
            if "center_score" in z.files:
                return instance, z["center_score"].reshape(-1).astype(np.float64)
    else:
        from fpcc_ros.evaluation import load_scene
        scene = load_scene(path)
        instance, points = scene.instance, scene.xyz
    return instance, centroid_scores(points, instance, part_radius)


def centroid_scores(xyz: np.ndarray, instance: np.ndarray, part_radius: float) -> np.ndarray:
    """1 - (|p - c| / d_max)^2 clipped to [0, 1], c = the centroid of the point's instance;
    0 for background and points with no return."""
    pts = np.nan_to_num(np.asarray(xyz, np.float64))
    size = np.maximum(np.bincount(instance, minlength=1), 1)
    center = np.stack([np.bincount(instance, weights=pts[:, d], minlength=len(size)) / size
                       for d in range(3)], axis=1)
    dist = np.linalg.norm(pts - center[instance], axis=1)
    score = np.clip(1.0 - (dist / part_radius) ** 2, 0.0, 1.0)
    return np.where(instance > 0, score, 0.0)


def oracle_for_scene(pipeline: Pipeline, path: Path,
                     heads: tuple[str, ...] = ORACLE_HEADS) -> OraclePipeline:
    """``pipeline`` with the scene at ``path``'s ground truth in place of its network's
    ``heads``."""
    instance, score = scene_truth(path, pipeline.config.part_radius)
    return OraclePipeline(pipeline, instance, score, heads)
