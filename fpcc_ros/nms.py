"""Non-maximum suppression on predicted center scores (paper Algorithm 1).

Points scoring above ``threshold`` are center candidates; the best remaining candidate becomes a
center and every candidate within ``radius`` (= screening_factor * d_max) of it is removed.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fpcc_ros.features import tile_order


# Kept centers found by direct distances before switching to a KD-tree over what is left: a
# scene has tens of centers, and for those a few passes over chunks of candidates are cheaper
# than building a tree; the tree bounds the cost when a poor score map yields thousands.
DIRECT_CENTERS = 64
# Candidates per chunk in the direct phase: a center's sphere is cleared in the chunks whose
# bounding boxes it reaches (100k points, 13.6k candidates, 30 centers: 1.8 ms, against 3.2 ms
# for passes over all remaining candidates in score order; 64 to 1024 per chunk all measured
# within 0.1 ms of that).
NMS_CHUNK = 256
# Above this many candidates the chunks are tiles (features.tile_order), not runs in cloud
# order: for a camera cloud a run is a strip across the bin, and a sphere reaches every strip it
# crosses (20 of 54 for the 40-part bench case; tiles 13). Below it, sorting costs more than it
# saves (the node's downsampled frames have 1-3k candidates).
TILED_CANDIDATES = 4096


def nms_centers(xyz: np.ndarray, scores: np.ndarray, threshold: float,
                radius: float) -> np.ndarray:
    """Indices into ``xyz`` of the selected centers, best first.

    Same result as :func:`nms_reference`. For the first :data:`DIRECT_CENTERS` centers the best
    remaining candidate is an argmax over the candidates' scores (suppressed ones set to -inf;
    argmax's first-index rule is the reference's tie-break) and its sphere is cleared in the
    chunks of candidates whose bounding boxes it reaches (whole chunks, as coordinate columns:
    clearing a suppressed candidate again is harmless); then a KD-tree over the candidates still
    left takes over.
    """
    candidates = np.flatnonzero(scores > threshold)
    if len(candidates) == 0:
        return candidates
    pts = np.take(np.asarray(xyz, dtype=np.float64), candidates, axis=0)
    work = np.array(scores[candidates], dtype=np.float64)  # -inf once suppressed or kept
    r2 = float(radius) * float(radius)
    # chunks of NMS_CHUNK candidates in tile order, as (3, chunks, NMS_CHUNK) coordinate columns
    # (the last chunk padded with inf, which no sphere reaches); work and keep stay in
    # candidate order, so argmax breaks ties as the reference does
    order = tile_order(pts, NMS_CHUNK) if len(pts) > TILED_CANDIDATES else np.arange(len(pts))
    chunks = -(-len(pts) // NMS_CHUNK)
    columns = np.full((3, chunks * NMS_CHUNK), np.inf)
    columns[:, :len(pts)] = np.take(pts, order, axis=0).T
    starts = np.arange(0, len(pts), NMS_CHUNK)
    lo = np.minimum.reduceat(columns[:, :len(pts)], starts, axis=1).T
    hi = np.maximum.reduceat(columns[:, :len(pts)], starts, axis=1).T
    columns = columns.reshape(3, chunks, NMS_CHUNK)
    keep: list[int] = []
    while len(keep) < DIRECT_CENTERS:
        best = int(np.argmax(work))
        if work[best] == -np.inf:
            return candidates[np.asarray(keep, dtype=np.int64)]
        keep.append(best)
        p = pts[best]
        gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        reached = np.flatnonzero(np.einsum("ij,ij->i", gap, gap) <= r2)   # its own, at least
        x, y, z = np.take(columns, reached, axis=1)       # (reached, NMS_CHUNK) each
        x -= p[0]
        y -= p[1]
        z -= p[2]
        x *= x
        x += y * y
        x += z * z
        hit = np.flatnonzero(x <= r2)
        work[np.take(order, reached[hit // NMS_CHUNK] * NMS_CHUNK + hit % NMS_CHUNK)] = -np.inf
    rest = np.flatnonzero(work > -np.inf)
    rest = rest[np.lexsort((rest, -work[rest]))]  # rank order; ties by index, as the reference
    keep += rest[_nms_tree(pts[rest], radius)].tolist()
    return candidates[np.asarray(keep, dtype=np.int64)]


def _nms_tree(pts: np.ndarray, radius: float) -> list[int]:
    """NMS over points already in rank order with a KD-tree: rows of ``pts`` kept."""
    tree = cKDTree(pts)
    suppressed = np.zeros(len(pts), dtype=bool)
    keep: list[int] = []
    for rank in range(len(pts)):
        if suppressed[rank]:
            continue
        keep.append(rank)
        suppressed[tree.query_ball_point(pts[rank], radius)] = True
    return keep


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
