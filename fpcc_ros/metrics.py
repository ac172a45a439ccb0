"""Instance-segmentation metrics as in the FPCC evaluation (DESIGN.md §4b).

Precision and recall at IoU >= 0.5 with one-to-one matching, MUCov and MWCov. Counts are
returned (not ratios) so that scenes can be summed before dividing, as the paper does.
Two protocols: ``paper`` (every ground-truth instance counts) and ``visible`` (ground-truth
instances with fewer than ``min_visible`` points at 640x480 are removed, points and all).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

IOU_THRESHOLD = 0.5
VISIBLE_MIN_POINTS = 300
REFERENCE_PIXELS = 640 * 480


@dataclass
class InstanceCounts:
    """Sufficient statistics of one or more scenes; add them, then read the ratios."""

    true_positives: int = 0
    predictions: int = 0
    ground_truths: int = 0
    cov_sum: float = 0.0            # sum over GT of best IoU (MUCov numerator)
    weighted_cov_sum: float = 0.0   # sum over GT of |gt| * best IoU (MWCov numerator)
    gt_points: int = 0              # sum over GT of |gt| (MWCov denominator)

    def __add__(self, other: "InstanceCounts") -> "InstanceCounts":
        return InstanceCounts(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    @property
    def precision(self) -> float:
        return self.true_positives / self.predictions if self.predictions else 0.0

    @property
    def recall(self) -> float:
        return self.true_positives / self.ground_truths if self.ground_truths else 0.0

    @property
    def mucov(self) -> float:
        return self.cov_sum / self.ground_truths if self.ground_truths else 0.0

    @property
    def mwcov(self) -> float:
        return self.weighted_cov_sum / self.gt_points if self.gt_points else 0.0

    def summary(self) -> dict[str, float | int]:
        return {"precision": self.precision, "recall": self.recall, "mucov": self.mucov,
                "mwcov": self.mwcov, "true_positives": self.true_positives,
                "predictions": self.predictions, "ground_truths": self.ground_truths}


def iou_matrix(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU between every predicted instance (label > 0) and every GT instance (label > 0).

    Background GT points inside a prediction enlarge its union (they count against it).
    Returns ``(iou (P, G), pred_ids, gt_ids)``.
    """
    overlap = overlap_matrix(pred, gt)
    return overlap.iou, overlap.pred_ids, overlap.gt_ids


@dataclass
class Overlap:
    """Points shared by every predicted and GT instance (label > 0), and their sizes."""

    shared: np.ndarray      # (P, G) points in both
    pred_ids: np.ndarray    # (P,) predicted labels
    gt_ids: np.ndarray      # (G,) GT labels
    pred_sizes: np.ndarray  # (P,) points of each prediction, background GT points included
    gt_sizes: np.ndarray    # (G,)

    @property
    def iou(self) -> np.ndarray:
        """(P, G) intersection over union."""
        return self.shared / (self.pred_sizes[:, None] + self.gt_sizes[None, :] - self.shared)


def overlap_matrix(pred: np.ndarray, gt: np.ndarray) -> Overlap:
    """The counts behind :func:`iou_matrix` (the error breakdown of fpcc_ros.miss_causes needs
    the shares, not only the ratio)."""
    pred_ids = np.unique(pred[pred > 0])
    gt_ids = np.unique(gt[gt > 0])
    p = np.searchsorted(pred_ids, pred)
    g = np.searchsorted(gt_ids, gt)
    both = (pred > 0) & (gt > 0)
    shared = np.zeros((len(pred_ids), len(gt_ids)))
    np.add.at(shared, (p[both], g[both]), 1)
    return Overlap(shared=shared, pred_ids=pred_ids, gt_ids=gt_ids,
                   pred_sizes=np.bincount(p[pred > 0], minlength=len(pred_ids)),
                   gt_sizes=np.bincount(g[gt > 0], minlength=len(gt_ids)))


def match_instances(iou: np.ndarray, threshold: float = IOU_THRESHOLD) -> int:
    """Number of one-to-one matches at IoU >= threshold (greedy, highest IoU first)."""
    if iou.size == 0:
        return 0
    pairs = np.argwhere(iou >= threshold)
    order = np.argsort(-iou[pairs[:, 0], pairs[:, 1]], kind="stable")
    used_p, used_g, matches = set(), set(), 0
    for pi, gi in pairs[order]:
        if pi not in used_p and gi not in used_g:
            used_p.add(pi)
            used_g.add(gi)
            matches += 1
    return matches


def scene_counts(pred: np.ndarray, gt: np.ndarray, protocol: str = "visible",
                 min_visible: int | None = None) -> InstanceCounts:
    """Counts for one scene. ``pred`` and ``gt`` are flat label arrays over the same points
    (points with no measurement should be excluded by the caller or carry label 0 in both)."""
    pred = np.asarray(pred).reshape(-1).astype(np.int64)
    gt = np.asarray(gt).reshape(-1).astype(np.int64)
    if pred.shape != gt.shape:
        raise ValueError(f"prediction has {pred.size} points but ground truth has {gt.size}")
    keep = evaluated_points(gt, protocol, min_visible)
    pred, gt = pred[keep], gt[keep]
    iou, _, gt_ids = iou_matrix(pred, gt)
    gt_sizes = np.bincount(np.searchsorted(gt_ids, gt[gt > 0]), minlength=len(gt_ids))
    return counts_from_iou(iou, gt_sizes)


def evaluated_points(gt: np.ndarray, protocol: str, min_visible: int | None = None) -> np.ndarray:
    """Mask of the points a protocol scores: all under ``paper``; under ``visible`` the points of
    GT instances with fewer than ``min_visible`` points (default 300) are removed."""
    if protocol == "paper":
        return np.ones(len(gt), bool)
    if protocol != "visible":
        raise ValueError(f"protocol={protocol!r} is unknown; use 'paper' or 'visible'")
    limit = VISIBLE_MIN_POINTS if min_visible is None else min_visible
    sizes = np.bincount(gt, minlength=1)
    small = np.flatnonzero(sizes < limit)
    return ~np.isin(gt, small[small > 0])


def counts_from_iou(iou: np.ndarray, gt_sizes: np.ndarray) -> InstanceCounts:
    """Counts from the (P, G) IoU matrix of one scene and the G ground-truth sizes (a baseline
    sweep drops rows of one matrix instead of re-scoring every minimum cluster size)."""
    best = iou.max(axis=0) if iou.shape[0] else np.zeros(len(gt_sizes))
    return InstanceCounts(true_positives=match_instances(iou), predictions=iou.shape[0],
                          ground_truths=len(gt_sizes), cov_sum=float(best.sum()),
                          weighted_cov_sum=float((best * gt_sizes).sum()),
                          gt_points=int(gt_sizes.sum()))


def f1_score(counts: InstanceCounts) -> float:
    """2PR/(P+R) from counts: 2 TP / (predictions + ground truths)."""
    total = counts.predictions + counts.ground_truths
    return 2 * counts.true_positives / total if total else 0.0


def visible_threshold(num_pixels: int) -> int:
    """300 points at 640x480, scaled with the sensor resolution of the scene."""
    return max(1, round(VISIBLE_MIN_POINTS * num_pixels / REFERENCE_PIXELS))
