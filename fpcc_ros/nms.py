"""Non-maximum suppression on predicted center scores (paper Algorithm 1).

Points scoring above ``threshold`` are center candidates; the best remaining candidate becomes a
center and every candidate within ``radius`` (= screening_factor * d_max) of it is removed.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def nms_centers(xyz: np.ndarray, scores: np.ndarray, threshold: float, radius: float) -> np.ndarray:
    """Indices into ``xyz`` of the selected centers, best first.

    Same result as :func:`nms_reference`, but candidates are visited once in score order and only
    the kept ones query a KD-tree for what they suppress: O(m log m + K * neighbours) instead of
    O(K * m) distance evaluations.
    """
    candidates = np.flatnonzero(scores > threshold)
    if len(candidates) == 0:
        return candidates
    # Highest score first; ties broken by index, as the literal algorithm's argmax does.
    order = candidates[np.lexsort((candidates, -scores[candidates]))]
    cand_xyz = xyz[order]
    tree = cKDTree(cand_xyz)
    suppressed = np.zeros(len(order), dtype=bool)
    keep: list[int] = []
    for rank in range(len(order)):
        if suppressed[rank]:
            continue
        keep.append(rank)
        suppressed[tree.query_ball_point(cand_xyz[rank], radius)] = True
    return order[np.asarray(keep, dtype=np.int64)]


def nms_reference(xyz: np.ndarray, scores: np.ndarray, threshold: float, radius: float) -> np.ndarray:
    """Algorithm 1 written out literally; the yardstick the fast version is tested against."""
    remaining = [i for i in range(len(scores)) if scores[i] > threshold]
    centers: list[int] = []
    while remaining:
        best = max(remaining, key=lambda i: (scores[i], -i))
        centers.append(best)
        remaining = [i for i in remaining
                     if i != best and np.linalg.norm(xyz[i] - xyz[best]) > radius]
    return np.asarray(centers, dtype=np.int64)
