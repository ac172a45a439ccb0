"""Tuning the classical baselines the way a careful user would, so FPCC meets a fair opponent.

Both baselines (fpcc_ros.baseline: crop + floor/wall removal, then Euclidean clustering or
DBSCAN, small clusters dropped) have settings a user tunes on a few labelled scenes of their own:
the link distance (Euclidean tolerance = DBSCAN eps), DBSCAN's ``min_samples`` and the minimum
cluster size. :func:`sweep_scene` scores every setting of a :class:`Grid` on one scene;
:func:`choose` picks the best from counts summed over the tuning scenes by :data:`SELECTION_RULE`.
The evaluation then runs the chosen setting on every scene: the number reported is what that
user would reach, not a best case picked on the test set.

The sweep is cheap because each distance builds one radius graph (reused for every
``min_samples``) and each clustering is scored once: dropping clusters under a minimum size only
removes rows of its IoU matrix (the other clusters' IoUs are unchanged), so every minimum size
is scored from that matrix (fpcc_ros.metrics.counts_from_iou).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from fpcc_ros.baseline import VOXEL_PER_TOLERANCE, cluster_foreground, dbscan_foreground, \
    representative_graph
from fpcc_ros.dbscan import dbscan
from fpcc_ros.metrics import (InstanceCounts, counts_from_iou, evaluated_points, f1_score,
                              iou_matrix)

METHODS = ("euclidean", "dbscan")
METHOD_NAMES = {"euclidean": "Euclidean clustering", "dbscan": "DBSCAN"}
# Link distances as fractions of d_max: 2-20 mm for a 0.1 m part. Below ~2 % the gaps between
# scan points split parts; above ~20 % every touching pair merges.
DISTANCE_FRACTIONS = np.geomspace(0.02, 0.2, 10)
MIN_SAMPLES = (1, 2, 3, 5, 8, 12, 20, 30, 45)                 # input points, the point included
MIN_CLUSTER_SIZES = (1, 25, 50, 100, 200, 300, 400, 600, 800)  # input points
DEFAULT_TUNE_SCENES = 3
SELECTION_RULE = ("best F1 = 2PR/(P+R) of precision and recall summed over the tuning scenes, "
                  "per protocol; ties go to the smaller distance, then min_samples, then minimum "
                  "cluster size")


@dataclass(frozen=True, order=True)
class Setting:
    """One baseline configuration. Euclidean clustering has ``min_samples`` 1 (every point is a
    core point: DBSCAN at min_samples 1 *is* connected components)."""

    method: str
    distance: float          # m: Euclidean tolerance / DBSCAN eps
    min_samples: int
    min_cluster_size: int

    def describe(self) -> str:
        name = "tolerance" if self.method == "euclidean" else "eps"
        samples = f", min_samples {self.min_samples}" if self.method == "dbscan" else ""
        return (f"{METHOD_NAMES[self.method]}, {name} {self.distance * 1e3:g} mm{samples}, "
                f"min cluster {self.min_cluster_size}")

    def to_json(self) -> dict:
        out = {"method": self.method, "distance_m": self.distance,
               "min_cluster_size": self.min_cluster_size}
        if self.method == "dbscan":
            out["min_samples"] = self.min_samples
        return out

    def run(self, xyz: np.ndarray, foreground: np.ndarray) -> np.ndarray:
        """(N,) uint32 labels of this setting over the foreground points."""
        if self.method == "euclidean":
            return cluster_foreground(xyz, foreground, self.distance, self.min_cluster_size)
        return dbscan_foreground(xyz, foreground, self.distance, self.min_samples,
                                 self.min_cluster_size)


@dataclass(frozen=True)
class Grid:
    """The settings tried: every distance x min_samples (DBSCAN) x minimum cluster size."""

    distances: tuple[float, ...]
    min_samples: tuple[int, ...] = MIN_SAMPLES
    min_cluster_sizes: tuple[int, ...] = MIN_CLUSTER_SIZES

    def __post_init__(self) -> None:
        for name, values, ok, what in (
                ("distances", self.distances, lambda v: np.isfinite(v) and v > 0,
                 "positive lengths in metres"),
                ("min_samples", self.min_samples, lambda v: int(v) == v and v >= 1,
                 "integers >= 1"),
                ("min_cluster_sizes", self.min_cluster_sizes, lambda v: int(v) == v and v >= 1,
                 "integers >= 1")):
            if not values or not all(ok(v) for v in values):
                raise ValueError(f"baseline {name} {list(values)} must be {what}")
        object.__setattr__(self, "distances", tuple(sorted({float(d) for d in self.distances})))
        object.__setattr__(self, "min_samples", tuple(sorted({int(v) for v in self.min_samples})))
        object.__setattr__(self, "min_cluster_sizes",
                           tuple(sorted({int(v) for v in self.min_cluster_sizes})))

    def settings(self, method: str) -> list[Setting]:
        """In selection order (ascending), so the first best wins ties."""
        samples = self.min_samples if method == "dbscan" else (1,)
        return [Setting(method, d, s, m) for d in self.distances for s in samples
                for m in self.min_cluster_sizes]

    def to_json(self) -> dict:
        return {"distance_m": list(self.distances), "min_samples": list(self.min_samples),
                "min_cluster_size": list(self.min_cluster_sizes)}


def default_distances(part_radius: float) -> list[float]:
    """The distance sweep for parts of this d_max, in metres (rounded to 0.1 mm)."""
    return sorted({round(float(f * part_radius), 4) for f in DISTANCE_FRACTIONS} - {0.0})


def sweep_scene(xyz: np.ndarray, foreground: np.ndarray, gt: np.ndarray, scored: np.ndarray,
                protocols: Sequence[str], min_visible: int, grid: Grid,
                methods: Iterable[str] = METHODS) -> dict[Setting, dict[str, InstanceCounts]]:
    """Counts of every setting of ``grid`` on one scene.

    ``gt`` is the ground truth of the ``scored`` points (those with a return), as the
    evaluation scores FPCC; ``foreground`` is the baseline's crop + plane removal mask.
    """
    idx = np.flatnonzero(foreground)
    keep = {p: evaluated_points(gt, p, min_visible) for p in protocols}
    out: dict[Setting, dict[str, InstanceCounts]] = {}
    for method in methods:
        for distance in grid.distances:
            if method == "euclidean":
                clusterings = {1: cluster_foreground(xyz, foreground, distance, 1)}
            else:
                clusterings = _dbscan_by_min_samples(xyz, idx, distance, grid.min_samples)
            for samples, labels in clusterings.items():
                for p, by_size in _score_by_min_size(labels[scored], gt, keep,
                                                     grid.min_cluster_sizes).items():
                    for size, counts in by_size.items():
                        out.setdefault(Setting(method, distance, samples, size), {})[p] = counts
    return out


def choose(totals: dict[Setting, dict[str, InstanceCounts]], method: str,
           protocol: str) -> Setting | None:
    """The setting of ``method`` with the best F1 of its summed counts (:data:`SELECTION_RULE`)."""
    best, best_f1 = None, -1.0
    for setting in sorted(s for s in totals if s.method == method):
        f1 = f1_score(totals[setting][protocol])
        if f1 > best_f1:
            best, best_f1 = setting, f1
    return best


def _dbscan_by_min_samples(xyz: np.ndarray, idx: np.ndarray, eps: float,
                           min_samples: Sequence[int]) -> dict[int, np.ndarray]:
    """DBSCAN labels (no minimum size) at one eps for every ``min_samples``: one graph."""
    out = {}
    if len(idx) == 0:
        return {s: np.zeros(len(xyz), np.uint32) for s in min_samples}
    reps, weights, inverse, pairs = representative_graph(xyz, idx, eps,
                                                         eps * VOXEL_PER_TOLERANCE)
    for samples in min_samples:
        labels = np.zeros(len(xyz), np.uint32)
        labels[idx] = dbscan(reps, eps, samples, 1, weights=weights, pairs=pairs)[inverse]
        out[samples] = labels
    return out


def _score_by_min_size(labels: np.ndarray, gt: np.ndarray, keep: dict[str, np.ndarray],
                       min_sizes: Sequence[int]) -> dict[str, dict[int, InstanceCounts]]:
    """Counts per protocol and minimum cluster size. A cluster's size is counted over all its
    points (what the baseline sees), its IoU over the points the protocol scores."""
    labels = labels.astype(np.int64)
    sizes = np.bincount(labels)
    out = {}
    for p, mask in keep.items():
        pred, truth = labels[mask], gt[mask]
        iou, pred_ids, gt_ids = iou_matrix(pred, truth)
        gt_sizes = np.bincount(np.searchsorted(gt_ids, truth[truth > 0]), minlength=len(gt_ids))
        rows = sizes[pred_ids]
        out[p] = {m: counts_from_iou(iou[rows >= m], gt_sizes) for m in min_sizes}
    return out
