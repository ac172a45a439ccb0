"""Where a scene's errors come from: each missed part and each extra instance, put down to
one stage (``fpcc eval`` prints the totals).

F1 says how many parts were missed; this says which stage to work on. A visible GT part
without a match (IoU >= 0.5) was missed because
  ``no_center``   no point of it scored a center above θ (the center head),
  ``suppressed``  it had candidates, but NMS kept none on it (a neighbour's center won),
  ``unlabelled``  it had a center, but most of its points got no instance (the clustering or
                  the small-instance filter dropped them),
  ``merged``      one instance holds most of it, together with other parts (clustering),
  ``split``       its points are spread over several instances, none holding half (clustering).
A prediction without a match is ``piece`` (most of its points from one part: a fragment of a
split part), ``spans_parts`` (from several parts, none holding half) or ``background`` (most
of its points on no part: floor, tote, the points of parts too small to count).
The causes are tested in this order; the first that holds is the cause.
"""
from __future__ import annotations

import numpy as np

from fpcc_ros.metrics import IOU_THRESHOLD, evaluated_points, overlap_matrix

MISS_CAUSES = ("no_center", "suppressed", "unlabelled", "merged", "split")
EXTRA_CAUSES = ("piece", "spans_parts", "background")


def error_causes(pred: np.ndarray, gt: np.ndarray, center_score: np.ndarray,
                 center_points: np.ndarray | None, score_threshold: float,
                 min_visible: int) -> dict[str, dict[str, int]]:
    """Counts of missed visible parts and of unmatched predictions by cause.

    ``pred``, ``gt`` and ``center_score`` are flat and index-aligned over the same points;
    ``center_points`` indexes the points on which NMS kept a center (None: not known, and no
    part is counted as ``suppressed``). Scored under the visible protocol, as the goals are.
    """
    keep = evaluated_points(gt, "visible", min_visible)
    on_center = np.zeros(len(gt), bool)
    if center_points is not None:
        on_center[center_points] = True
    pred, gt, score, on_center = pred[keep], gt[keep], center_score[keep], on_center[keep]
    overlap = overlap_matrix(pred, gt)
    shared, iou = overlap.shared, overlap.iou

    part = np.searchsorted(overlap.gt_ids, gt)[gt > 0]  # GT column of each point on a part
    top_score = np.zeros(len(overlap.gt_ids))
    np.maximum.at(top_score, part, score[gt > 0])
    centers = np.bincount(part, weights=on_center[gt > 0], minlength=len(overlap.gt_ids))
    unlabelled = np.bincount(part, weights=pred[gt > 0] == 0, minlength=len(overlap.gt_ids))
    sizes = overlap.gt_sizes
    largest_share = shared.max(axis=0) / sizes if len(shared) else np.zeros(len(sizes))
    missed = iou.max(axis=0) < IOU_THRESHOLD if len(shared) else np.ones(len(sizes), bool)
    cause = np.select([top_score < score_threshold,
                       (centers == 0) & (center_points is not None),
                       unlabelled > sizes / 2, largest_share > 0.5],
                      MISS_CAUSES[:4], MISS_CAUSES[4])[missed]

    extra = iou.max(axis=1) < IOU_THRESHOLD if shared.shape[1] else \
        np.ones(len(shared), bool)
    on_parts = shared.sum(axis=1) / np.maximum(overlap.pred_sizes, 1)
    top_part = shared.max(axis=1, initial=0) / np.maximum(overlap.pred_sizes, 1)
    kind = np.select([on_parts < 0.5, top_part >= 0.5], ["background", "piece"],
                     "spans_parts")[extra]
    return {"missed": {c: int((cause == c).sum()) for c in MISS_CAUSES},
            "extra": {c: int((kind == c).sum()) for c in EXTRA_CAUSES}}


def describe(causes: dict[str, dict[str, int]]) -> list[str]:
    """Two summary lines: missed parts and extra instances by cause."""
    def line(title: str, counts: dict[str, int], names: dict[str, str]) -> str:
        total = sum(counts.values())
        parts = ", ".join(f"{names[c]} {n}" for c, n in counts.items())
        return f"{title} ({total}): {parts}"
    return [line("missed visible parts", causes["missed"],
                 {"no_center": "no center above θ", "suppressed": "center suppressed by NMS",
                  "unlabelled": "left unlabelled", "merged": "merged with others",
                  "split": "split"}),
            line("extra instances", causes["extra"],
                 {"piece": "a piece of one part", "spans_parts": "across parts",
                  "background": "mostly background"})]


def add_causes(total: dict[str, dict[str, int]] | None,
               scene: dict[str, dict[str, int]]) -> dict[str, dict[str, int]]:
    """Sum of two breakdowns (``total`` None: the first scene)."""
    if total is None:
        return {k: dict(v) for k, v in scene.items()}
    return {k: {c: total[k][c] + n for c, n in v.items()} for k, v in scene.items()}
