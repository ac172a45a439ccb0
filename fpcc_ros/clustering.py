"""Clustering in feature space around the NMS centers (paper §3.2).

Every point joins the center nearest in the embedding space; the paper's noise rule gives a
point no instance when that center is farther than d_max in 3D. We also reject points whose
embedding is farther than ``feature_gate`` from every admissible center: background (tote,
floor) is trained to sit at least eps2 = 1 away from part centers, so without the gate every
floor point near a part would be painted as part of it.
"""
from __future__ import annotations

import numpy as np


def assign_to_centers(xyz: np.ndarray, embedding: np.ndarray, centers: np.ndarray,
                      d_max: float, feature_gate: float = np.inf) -> np.ndarray:
    """Labels 1..K (0 = none): nearest center in feature space among centers within d_max in 3D.

    Restricting the search to spatial neighbours is the fast path's rule; it agrees with the
    paper's rule (:func:`assign_reference`) whenever the globally nearest center in feature space
    is itself within d_max, and otherwise assigns the point to the best admissible center
    instead of discarding it.
    """
    return assign_to_center_points(xyz, embedding, xyz[centers], embedding[centers], d_max,
                                   feature_gate)


ROW_CHUNK = 4096  # points per pass: the (chunk, centers) temporaries stay in cache


def assign_to_center_points(xyz: np.ndarray, embedding: np.ndarray, center_xyz: np.ndarray,
                            center_embedding: np.ndarray, d_max: float,
                            feature_gate: float = np.inf) -> np.ndarray:
    """:func:`assign_to_centers` with the centers given by position and embedding, for when the
    centers' embeddings come from another network pass than the points' own rows.

    Only (point, center) pairs within d_max in 3D can be chosen, and in a bin they are a few per
    cent of all pairs (100k points x 18 centers: 49k of 1.8M). So, per chunk of points: 3D
    distances to the centers near the chunk's bounding box, then embedding dot products for just
    the points and centers that have an admissible pair. The choice per point is the one of
    the dense rule: the admissible center nearest in feature space, then the gate. The small
    products use numpy's own loops, not BLAS: OpenBLAS wakes its thread pool for each one,
    which on a 2-core machine busy with onnxruntime costs more than the product.
    """
    n = len(xyz)
    labels = np.zeros(n, dtype=np.int32)
    if len(center_xyz) == 0 or n == 0:
        return labels
    cxyz = np.asarray(center_xyz, dtype=np.float64)
    cemb = np.asarray(center_embedding, dtype=np.float32)
    cemb_sq = np.einsum("ij,ij->i", cemb, cemb)
    d2 = float(d_max) * float(d_max)
    gate2 = float(feature_gate) * float(feature_gate)
    cols_xyz = np.array(xyz, dtype=np.float64).T.copy()  # x, y, z rows: contiguous per chunk
    for start in range(0, n, ROW_CHUNK):
        px, py, pz = cols_xyz[:, start:start + ROW_CHUNK]
        lo = np.array([px.min(), py.min(), pz.min()])
        hi = np.array([px.max(), py.max(), pz.max()])
        gap = np.maximum(np.maximum(lo - cxyz, cxyz - hi), 0.0)   # center to the chunk's box
        near = np.flatnonzero(np.einsum("ij,ij->i", gap, gap) <= d2)
        if len(near) == 0:
            continue
        c = cxyz[near]
        space = (px[:, None] - c[None, :, 0]) ** 2
        space += (py[:, None] - c[None, :, 1]) ** 2
        space += (pz[:, None] - c[None, :, 2]) ** 2
        admissible = space <= d2
        rows = np.flatnonzero(admissible.any(axis=1))
        if len(rows) == 0:
            continue
        cols = np.flatnonzero(admissible[rows].any(axis=0))
        e = np.asarray(embedding[start + rows], dtype=np.float32)
        # |e - c|^2 = |e|^2 - 2 e.c + |c|^2; the argmin needs only the last two terms
        feat = np.einsum("ik,jk->ij", e, cemb[near[cols]])  # no BLAS threads for a small product
        feat *= -2.0
        feat += cemb_sq[near[cols]]
        np.putmask(feat, ~admissible[np.ix_(rows, cols)], np.inf)
        best = np.argmin(feat, axis=1)
        best_sq = feat[np.arange(len(rows)), best] + np.einsum("ij,ij->i", e, e)
        ok = np.isfinite(best_sq) & (best_sq <= gate2)
        labels[start + rows[ok]] = (near[cols[best[ok]]] + 1).astype(np.int32)
    return labels


def assign_reference(xyz: np.ndarray, embedding: np.ndarray, centers: np.ndarray,
                     d_max: float, feature_gate: float = np.inf) -> np.ndarray:
    """The paper's rule, one point at a time: nearest center in feature space; noise if that
    center is farther than d_max in 3D (or farther than ``feature_gate`` in feature space)."""
    labels = np.zeros(len(xyz), dtype=np.int32)
    if len(centers) == 0:
        return labels
    for i in range(len(xyz)):
        feat = [np.linalg.norm(embedding[i] - embedding[c]) for c in centers]
        k = int(np.argmin(feat))
        if np.linalg.norm(xyz[i] - xyz[centers[k]]) <= d_max and feat[k] <= feature_gate:
            labels[i] = k + 1
    return labels
