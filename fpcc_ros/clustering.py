"""Clustering in feature space around the NMS centers (paper §3.2).

Every point joins the center nearest in the embedding space; the paper's noise rule gives a
point no instance when that center is farther than d_max in 3D. We also reject points whose
embedding is farther than ``feature_gate`` from every admissible center: background (tote,
floor) is trained to sit at least eps2 = 1 away from part centers, so without the gate every
floor point near a part would be painted as part of it.
"""
from __future__ import annotations

import numpy as np


def _squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) squared Euclidean distances via one GEMM (no (n, m, d) temporary)."""
    a = a.astype(np.float32, copy=False)
    b = b.astype(np.float32, copy=False)
    sq = np.einsum("ij,ij->i", a, a)[:, None] - 2.0 * (a @ b.T) + np.einsum("ij,ij->i", b, b)[None, :]
    return np.maximum(sq, 0.0, out=sq)


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


def assign_to_center_points(xyz: np.ndarray, embedding: np.ndarray, center_xyz: np.ndarray,
                            center_embedding: np.ndarray, d_max: float,
                            feature_gate: float = np.inf) -> np.ndarray:
    """:func:`assign_to_centers` with the centers given by position and embedding, for when the
    centers' embeddings come from another network pass than the points' own rows."""
    n = len(xyz)
    if len(center_xyz) == 0 or n == 0:
        return np.zeros(n, dtype=np.int32)
    feat_sq = _squared_distances(embedding, center_embedding)
    space_sq = _squared_distances(xyz, center_xyz)
    feat_sq[space_sq > d_max * d_max] = np.inf
    best = np.argmin(feat_sq, axis=1)
    best_sq = feat_sq[np.arange(n), best]
    labels = (best + 1).astype(np.int32)
    labels[~np.isfinite(best_sq) | (best_sq > feature_gate * feature_gate)] = 0
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
