"""Clustering in feature space around the NMS centers (paper §3.2).

Every point joins the center nearest in the embedding space; the paper's noise rule gives a
point no instance when that center is farther than d_max in 3D. We also reject points whose
embedding is farther than ``feature_gate`` from every admissible center: background (tote,
floor) is trained to sit at least eps2 = 1 away from part centers, so without the gate every
floor point near a part would be painted as part of it.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager, nullcontext
from functools import cache
from typing import TypeVar

import numpy as np

from fpcc_ros.extent import box_diagonals, fit_within


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
# Passes of at least this many points are split across cores (whole chunks per thread, so the
# labels are those of one thread). The node's blocks (2-3k points) stay on the calling thread,
# where handing work to a pool would cost more than it saves.
PARALLEL_ROWS = 2 * ROW_CHUNK
MAX_THREADS = 4  # the steps are memory-bound: beyond a few threads they gain little

_Result = TypeVar("_Result")


@cache
def _thread_pool() -> tuple[ThreadPoolExecutor, int] | None:
    """Threads for the chunk loops (numpy and single-threaded BLAS release the GIL), one per
    core this process may run on, created on first use, and their number; None on a single
    core."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    threads = min(MAX_THREADS, cores or 1)
    if threads < 2:
        return None
    return ThreadPoolExecutor(threads, thread_name_prefix="fpcc_cluster"), threads


_thread_limit = MAX_THREADS


@contextmanager
def chunk_threads(limit: int) -> Iterator[None]:
    """At most ``limit`` threads for the chunk loops inside the block (the benchmark times the
    100k-point case on one thread beside the default); not for use while another thread
    clusters."""
    global _thread_limit
    before, _thread_limit = _thread_limit, max(1, int(limit))
    try:
        yield
    finally:
        _thread_limit = before


def _over_row_ranges(n: int, work: Callable[[int, int], _Result]) -> list[_Result]:
    """``work(start, stop)`` over consecutive ranges of whole chunks covering rows 0..n: one
    range on the calling thread below :data:`PARALLEL_ROWS`, else one per pool thread.

    The callers' chunk loops are memory-bound numpy and small BLAS calls on one thread each; a
    100k-point pass (the NMS + clustering benchmark, full resolution) splits into a range per
    core. Chunk-aligned ranges give every row the chunk it has on one thread, so the results do
    not depend on the number of threads. Call inside :func:`single_thread_blas`.
    """
    pool = _thread_pool() if n >= PARALLEL_ROWS else None
    chunks = -(-n // ROW_CHUNK)
    parts = min(pool[1], chunks, _thread_limit) if pool is not None else 1
    if parts < 2:
        return [work(0, n)]
    bounds = [min(n, (chunks * i // parts) * ROW_CHUNK) for i in range(parts + 1)]
    return list(pool[0].map(work, bounds[:-1], bounds[1:]))


@cache
def _blas_controller():
    """threadpoolctl's view of the loaded BLAS libraries (found once: the scan takes ~ms), or
    None without threadpoolctl."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    return ThreadpoolController()


def single_thread_blas() -> AbstractContextManager:
    """BLAS pinned to the calling thread from this call until the block exits, when
    threadpoolctl can do it (use it directly in a ``with``: the limit is set on creation).

    The assignment's products are small (tens of thousands of rows x tens of centers): one
    thread computes one in about a millisecond, while OpenBLAS's default pool, woken for it on a
    2-core machine where onnxruntime or another process keeps the other core busy, measured
    190 ms for the same work (100k points, 30 centers, while a training run loaded the machine).
    """
    controller = _blas_controller()
    return nullcontext() if controller is None else controller.limit(limits=1, user_api="blas")


def _center_products(e: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """``e @ centers.T``: one single-threaded BLAS call, or numpy's own loops (same values up to
    rounding, ~2x slower) when BLAS cannot be pinned to one thread."""
    if _blas_controller() is None:
        return np.einsum("ik,jk->ij", e, centers)
    return e @ centers.T


def _rows(embedding: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``embedding[index]`` as float32: on a contiguous array ``np.take`` gathers rows ~1.6x
    faster than fancy indexing (1k of 100k rows of 128: 22 vs 34 us; the 100k-point
    assignment, whose gathers are about a fifth of its time: 6-13 % faster). On a strided view
    (a sample) ``np.take`` would first copy the whole array, so fancy indexing stays."""
    rows = np.take(embedding, index, axis=0) if embedding.flags.c_contiguous else embedding[index]
    return np.asarray(rows, dtype=np.float32)


# Added to the feature distance of a (point, center) pair outside d_max: an arithmetic penalty
# instead of a boolean-mask assignment, which cost 1.1 ms of the 7.6 ms assignment of the
# 100k-point / 42-center bench case (the penalty: 0.08 ms). Squared embedding distances are
# O(10), so a penalised pair never wins while an admissible one exists.
_OUTSIDE = np.float32(1e30)


def _chunk_neighbourhoods(xyz: np.ndarray, center_xyz: np.ndarray, radius: float
                          ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Per chunk of :data:`ROW_CHUNK` consecutive points: its first row, the centers within
    ``radius`` of its bounding box, and which of its points lie within ``radius`` of each of
    those, as a (centers, points) bool array.

    Consecutive points of a cloud (image order for an organized one) are close in space, so a
    chunk's box reaches only the centers around it and the rest are never compared.
    """
    n = len(xyz)
    cxyz = np.asarray(center_xyz, dtype=np.float64)
    cxyz32 = cxyz.astype(np.float32)
    r2 = float(radius) * float(radius)
    cols_xyz = np.empty((3, n), np.float32)
    cols_xyz[:] = np.asarray(xyz).T    # x, y, z rows: contiguous per chunk
    starts = np.arange(0, n, ROW_CHUNK)
    # every chunk's bounding box at once, then the centers within radius of each box
    lo = np.minimum.reduceat(cols_xyz, starts, axis=1).T.astype(np.float64)  # (chunks, 3)
    hi = np.maximum.reduceat(cols_xyz, starts, axis=1).T.astype(np.float64)
    gap = np.maximum(np.maximum(lo[:, None] - cxyz[None], cxyz[None] - hi[:, None]), 0.0)
    near_chunk = np.einsum("cjk,cjk->cj", gap, gap) <= r2                      # (chunks, m)
    for k, start in enumerate(starts.tolist()):
        near = np.flatnonzero(near_chunk[k])
        if len(near) == 0:
            continue
        px, py, pz = cols_xyz[:, start:start + ROW_CHUNK]
        c = cxyz32[near]
        # (centers, points) layout: the reductions over centers run along contiguous rows
        space = (px[None, :] - c[:, 0:1]) ** 2
        space += (py[None, :] - c[:, 1:2]) ** 2
        space += (pz[None, :] - c[:, 2:3]) ** 2
        yield start, near, space <= r2


def assign_to_center_points(xyz: np.ndarray, embedding: np.ndarray, center_xyz: np.ndarray,
                            center_embedding: np.ndarray, d_max: float,
                            feature_gate: float = np.inf) -> np.ndarray:
    """:func:`assign_to_centers` with the centers given by position and embedding, for when the
    centers' embeddings come from another network pass than the points' own rows.

    Only (point, center) pairs within d_max in 3D can be chosen, and in a bin they are a few per
    cent of all pairs (100k points x 18 centers: 49k of 1.8M). So, per chunk of points
    (:func:`_chunk_neighbourhoods`): a point with one admissible center only needs the gate
    (one dot product), one with several the embedding dot products with those (one BLAS product
    per chunk, on the calling thread: see :func:`single_thread_blas`). The choice per point is
    the one of the dense rule: the admissible center nearest in feature space, then the gate.
    """
    n = len(xyz)
    if len(center_xyz) == 0 or n == 0:
        return np.zeros(n, dtype=np.int32)
    cemb = np.asarray(center_embedding, dtype=np.float32)

    def assign_rows(start: int, stop: int) -> np.ndarray:
        return _assign_rows(xyz[start:stop], embedding[start:stop], center_xyz, cemb, d_max,
                            feature_gate)

    with single_thread_blas():  # applies on entry to every BLAS call, on every thread
        parts = _over_row_ranges(n, assign_rows)
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _assign_rows(xyz: np.ndarray, embedding: np.ndarray, center_xyz: np.ndarray,
                 cemb: np.ndarray, d_max: float, feature_gate: float) -> np.ndarray:
    """:func:`assign_to_center_points` on one thread, chunk by chunk."""
    labels = np.zeros(len(xyz), dtype=np.int32)
    cemb_sq = np.einsum("ij,ij->i", cemb, cemb)
    gate2 = float(feature_gate) * float(feature_gate)
    for start, near, admissible in _chunk_neighbourhoods(xyz, center_xyz, d_max):
        count = admissible.sum(axis=0, dtype=np.int32)
        # one admissible center (most points): it is the choice; only the gate needs |e - c|
        one = np.flatnonzero(count == 1)
        if len(one):
            pick = near[np.argmax(admissible[:, one], axis=0)]
            e = _rows(embedding, start + one)
            dist_sq = (np.einsum("ij,ij->i", e, e)
                       - 2.0 * np.einsum("ij,ij->i", e, cemb[pick]) + cemb_sq[pick])
            ok = dist_sq <= gate2
            labels[start + one[ok]] = (pick[ok] + 1).astype(np.int32)
        # several: the nearest in feature space among them
        rows = np.flatnonzero(count > 1)
        if len(rows) == 0:
            continue
        e = _rows(embedding, start + rows)
        # |e - c|^2 = |e|^2 - 2 e.c + |c|^2; the argmin needs only the last two terms.
        # (rows, centers) layout: the product is one BLAS call in its fastest order
        feat = _center_products(e, cemb[near])
        feat *= -2.0
        feat += cemb_sq[near]
        outside = (~np.take(admissible, rows, axis=1)).view(np.uint8).astype(np.float32)
        outside *= _OUTSIDE
        feat += outside.T
        best = np.argmin(feat, axis=1)
        best_sq = np.take_along_axis(feat, best[:, None], axis=1)[:, 0]
        best_sq += np.einsum("ij,ij->i", e, e)
        ok = best_sq <= gate2
        labels[start + rows[ok]] = (near[best[ok]] + 1).astype(np.int32)
    return labels


# The loss pulls points of one instance within eps1 of each other in feature space.
PULL_MARGIN = 0.5
PROTOTYPE_ROWS = 16_384  # a prototype is a mean: beyond this many rows, a uniform sample


def center_prototypes(xyz: np.ndarray, embedding: np.ndarray, center_rows: np.ndarray,
                      radius: float, pull: float = PULL_MARGIN,
                      max_rows: int = PROTOTYPE_ROWS) -> np.ndarray:
    """(m, D) embedding standing for each center: the mean over the points within ``radius``
    of it in 3D whose embeddings lie within ``pull`` of the center's own.

    The paper compares every point with the center point's embedding, one noisy sample of its
    instance's. The hinge loss puts the instance's points within eps1 = ``pull`` of each other,
    so the mean of the center's neighbours that are that close in feature space estimates the
    instance's embedding with the noise averaged out; neighbours of another part (beyond eps2)
    are left out. ``xyz`` and ``embedding`` are one network pass's rows; ``center_rows`` index
    them. radius 0 gives the centers' own embeddings.

    A pass of more than ``max_rows`` rows (full resolution: every valid point through the
    network) is sampled with a uniform stride: the mean of ~100 of a center's neighbours
    estimates it as well as the mean of ~1,000, at a fraction of the cost (100k rows: 5.6 ->
    1.5 ms). Passes of the voxel-downsampled path (2-16k rows) use every row.
    """
    own = np.asarray(embedding[center_rows], dtype=np.float32)
    if radius <= 0 or len(center_rows) == 0:
        return own
    stride = max(1, -(-len(xyz) // max_rows))
    sample_xyz, sample_emb = xyz[::stride], embedding[::stride]
    center_xyz = xyz[center_rows]

    def like_sums(start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        return _like_neighbour_sums(sample_xyz[start:stop], sample_emb[start:stop],
                                    center_xyz, own, radius, pull)

    with single_thread_blas():
        parts = _over_row_ranges(len(sample_xyz), like_sums)
    sums, counts = parts[0] if len(parts) == 1 else map(sum, zip(*parts))
    # unsampled, each center is its own neighbour (distance 0); sampled, one may have no like
    # neighbour among the sample, and keeps its own embedding
    return np.where(counts[:, None] > 0, sums / np.maximum(counts, 1.0)[:, None], own)


def _like_neighbour_sums(xyz: np.ndarray, embedding: np.ndarray, center_xyz: np.ndarray,
                         own: np.ndarray, radius: float, pull: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per center, the sum and the number of the embeddings of ``xyz``'s rows within
    ``radius`` of it in 3D and within ``pull`` of ``own`` in feature space; one thread."""
    own_sq = np.einsum("ij,ij->i", own, own)
    sums = np.zeros_like(own)
    counts = np.zeros(len(own), np.float32)
    for start, near, within in _chunk_neighbourhoods(xyz, center_xyz, radius):
        rows = np.flatnonzero(within.any(axis=0))
        if len(rows) == 0:
            continue
        e = _rows(embedding, start + rows)
        feature_sq = (np.einsum("ij,ij->i", e, e)[:, None]
                      - 2.0 * _center_products(e, own[near]) + own_sq[near])  # (rows, m)
        weight = (within[:, rows].T & (feature_sq <= pull * pull)).astype(np.float32)
        sums[near] += weight.T @ e
        counts[near] += weight.sum(axis=0)
    return sums, counts


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


def close_center_pairs(center_xyz: np.ndarray, center_embedding: np.ndarray, d_max: float,
                       max_distance: float) -> np.ndarray:
    """(m, 2) index pairs i < j of centers within 2 d_max of each other in 3D whose embeddings
    are closer than ``max_distance``: candidates for one part.

    NMS keeps one center per screening sphere, but an elongated part (a shaft: d_max several
    times its width) fits two centers farther apart than the sphere when the screening radius
    is small enough not to suppress its parallel neighbours. The network puts points of one
    instance within eps1 (0.5) of each other and those of other instances within 2 d_max (the
    valid-distance matrix of the loss) beyond eps2 (1.0), so within 2 d_max the embedding
    distance tells the two cases apart. Embeddings must come from one network pass.
    Pairs come most alike first: the order :func:`merge_centers` joins them in.
    """
    if len(center_xyz) < 2:
        return np.zeros((0, 2), np.int64)
    near = np.linalg.norm(center_xyz[:, None] - center_xyz[None], axis=2) < 2 * d_max
    # |a - b|^2 from the Gram matrix: (m, m) work instead of (m, m, D)
    e = np.asarray(center_embedding, dtype=np.float64)
    sq = np.einsum("ij,ij->i", e, e)
    feature_sq = sq[:, None] + sq[None] - 2.0 * (e @ e.T)
    i, j = np.nonzero(np.triu(near & (feature_sq < max_distance * max_distance), k=1))
    order = np.argsort(feature_sq[i, j], kind="stable")
    return np.stack([i[order], j[order]], axis=1)


def merge_labels(labels: np.ndarray, num_centers: int, pairs: np.ndarray) -> np.ndarray:
    """``labels`` (center rank + 1, 0 = none) with the centers of each group that
    :func:`merge_centers` makes of ``pairs`` carrying one label."""
    group = merge_centers(num_centers, pairs)
    return np.concatenate([[0], group + 1]).astype(labels.dtype)[labels]


def merge_centers(num_centers: int, pairs: np.ndarray) -> np.ndarray:
    """Group of each center (its lowest-ranked member): the labels of merged centers become
    one instance. ``pairs`` index centers 0..num_centers-1, in order of preference.

    Complete linkage: a pair joins two groups only when every center of one is paired with
    every center of the other. Two centers of one part lie within 2 d_max of each other, so a
    group whose members are not all pairwise close is more than one part; joining whole
    connected sets instead chains a row of touching parallel parts (A like B, B like C) into
    one instance. Centers of one part are all pairwise alike, so they still end up together.
    """
    group = np.arange(num_centers)
    if num_centers == 0 or len(pairs) == 0:
        return group
    linked = np.zeros((num_centers, num_centers), bool)
    linked[pairs[:, 0], pairs[:, 1]] = True
    linked |= linked.T
    for i, j in pairs:        # a few dozen centers: the loop is over pairs, not points
        a, b = group[i], group[j]
        if a != b and linked[np.ix_(group == a, group == b)].all():
            group[(group == a) | (group == b)] = min(a, b)
    return group


# A center claims a fragment when its labels there are at least this share of all its labels
# or of the fragment (counted in input points): a piece of its part, not a stray bit.
CLAIM_SHARE = 0.2
# A fragment no center claims is kept when its bounding-box diagonal is at most this many d_max:
# up to two touching parts (such a pair still matches its larger part at IoU >= 0.5, as DBSCAN's
# clusters do), not the tote's walls. At 2 (one part) the shipped model's ring-screw F1 was
# 0.567 instead of 0.583 (gear shaft 0.609 instead of 0.602; 5 validation piles each).
LEFTOVER_FIT = 4.0
# ... and when it is at least this share of the median bounding-box diagonal of the instances the
# centers found in the same frame: a piece cut off a part (a ring screw's eye, the far end of a
# shaft behind an occluder) is smaller than the parts around it, a whole part the network gave no
# center is not. 20 validation piles per IPA part, F1 without -> with: gear shaft 0.596 -> 0.604,
# ring screw 0.625 -> 0.642 (P 0.612 -> 0.679 and 0.576 -> 0.612); chosen on 8 + 8 other piles
# (0.4-0.8 in steps of 0.1; 0.6 the best mean: 0.629 -> 0.630 and 0.626 -> 0.638)
LEFTOVER_SHARE = 0.6


def connect_fragments(labels: np.ndarray, fragment: np.ndarray, weights: np.ndarray,
                      xyz: np.ndarray, d_max: float, min_points: int, join: float = 2.0,
                      claim_share: float = CLAIM_SHARE) -> np.ndarray:
    """Instance labels from point-wise center labels (``labels``: 1..C, 0 = none, e.g. the
    paper's nearest center) decided per geometric fragment (``fragment``: 1..K, 0 = noise, e.g.
    :func:`fpcc_ros.dbscan.dbscan`'s). Votes are counted in input points (``weights`` per row).

    Connectivity knows where a part ends unless it touches another; the centers know which
    pieces are one part unless the network is wrong. A center *claims* a fragment where its
    labels are at least ``claim_share`` of all its labels or of the fragment (a piece of its
    part, or a fragment mostly its own; not a stray bit). Then:

    * a claimed fragment that fits in a part (width at most 2 ``d_max``: no two of its points
      farther apart than a part's diameter, fpcc_ros.extent) is one
      part: all of it goes to its strongest claimant. A part cut in two by an occluder is two
      fragments claimed by one center: they join;
    * a larger claimed fragment is touching parts: a point keeps its label when that center
      claims the fragment (the paper's rule, point by point), so the centers split it;
    * a center whose pieces together do not fit in a box of diagonal ``join`` ``d_max`` keeps
      only the piece holding most of its points: a wrong vote does not chain parts across the
      bin. 2 is a whole part (a healthy network's setting); a network whose votes follow
      proximity more than identity needs less (the shipped one: 1.2, see the README);
    * what is left of each fragment (all of it when no center claims it: a part the network
      found no center for) is an instance of its own when it holds ``min_points`` input points
      and is no longer than two parts (:data:`LEFTOVER_FIT`; the tote's walls are) and not much
      shorter than the instances the centers found (:data:`LEFTOVER_SHARE`: a piece cut off a
      part is), else noise.

    Returns labels 1..C for the centers' instances, C+1.. for the kept leftovers (in fragment
    order), 0 for noise.
    """
    labels = np.asarray(labels, dtype=np.int64)
    fragment = np.asarray(fragment, dtype=np.int64)
    n = len(labels)
    c = int(labels.max(initial=0))
    out = np.zeros(n, np.int32)
    k = int(fragment.max(initial=0))
    if k == 0:
        return out
    w = np.asarray(weights, dtype=np.float64)
    pts = np.asarray(xyz, dtype=np.float64)
    votes = np.bincount(fragment * (c + 1) + labels, weights=w,
                        minlength=(k + 1) * (c + 1)).reshape(k + 1, c + 1)[:, 1:]
    size = np.bincount(fragment, weights=w, minlength=k + 1)
    claim = (votes >= claim_share * np.minimum(votes.sum(axis=0)[None, :], size[:, None])) \
        & (votes > 0)
    claim[0] = False
    claimed = claim.any(axis=1)

    # a claimed fragment the size of a part: its strongest claimant's, whole
    # width, not the bounding-box diagonal: the diagonal of a whole ring screw is 2.36 d_max
    # (median in the camera frame), so it was split point by point; 20 validation piles per
    # IPA part, shipped model at its card, F1 with the diagonal -> width: gear shaft 0.607 ->
    # 0.605, ring screw 0.658 -> 0.696 (8 + 8 other piles: 0.653 -> 0.654, 0.648 -> 0.703)
    fits = fit_within(pts, fragment, k, 2.0 * d_max)
    strongest = np.argmax(np.where(claim, votes, -1.0), axis=1) + 1 if c else np.zeros(k + 1, int)
    whole = fits & claimed
    in_whole = whole[fragment]
    out[in_whole] = strongest[fragment[in_whole]]
    # a larger one: its claimants' own labels, point by point
    own = (labels > 0) & ~in_whole & claimed[fragment]
    own[own] = claim[fragment[own], labels[own] - 1]
    out[own] = labels[own]
    # a center's pieces must fit in one part together, else it keeps its largest. Measured on
    # the bounding-box diagonal, as is a leftover's size below: `join` and the leftover rules
    # were tuned on it, and with widths the shipped model's gear-shaft F1 fell 0.654 -> 0.629
    # (8 piles, ring screw 0.703 -> 0.711; the 20 validation piles: 0.605 -> 0.577, 0.696 -> 0.701)
    out = _largest_piece_when_spread(out, fragment, w, pts, c, k, join * d_max)

    # leftovers, per fragment: an instance when big enough and small enough to be a part
    left = (out == 0) & (fragment > 0)
    left_size = np.bincount(fragment[left], weights=w[left], minlength=k + 1)
    keep = np.flatnonzero(left_size >= max(min_points, 1))
    keep = keep[keep > 0]
    if len(keep):
        diag = box_diagonals(pts[left], fragment[left], k)[keep]
        keep = keep[(diag <= LEFTOVER_FIT * d_max)
                    & (diag >= LEFTOVER_SHARE * _median_instance_diagonal(out, pts, c))]
        new_id = np.zeros(k + 1, np.int32)
        new_id[keep] = c + 1 + np.arange(len(keep), dtype=np.int32)
        out[left] = new_id[fragment[left]]
    return out


def _median_instance_diagonal(out: np.ndarray, pts: np.ndarray, c: int) -> float:
    """Median bounding-box diagonal of the instances 1..c in ``out`` (0 when there are none)."""
    present = np.bincount(out, minlength=c + 1)[1:] > 0
    if not present.any():
        return 0.0
    return float(np.median(box_diagonals(pts, out, c)[1:][present]))


def _largest_piece_when_spread(out: np.ndarray, fragment: np.ndarray, w: np.ndarray,
                               pts: np.ndarray, c: int, k: int, diagonal: float) -> np.ndarray:
    """``out`` with each label 1..c whose points' bounding box has a longer diagonal than
    ``diagonal`` kept on the fragment holding most of its points only (the rest: 0)."""
    rows = np.flatnonzero(out > 0)
    if len(rows) == 0:
        return out
    spread = box_diagonals(pts[rows], out[rows], c) > diagonal
    rows = rows[spread[out[rows]]]
    if len(rows) == 0:
        return out
    piece = np.bincount(out[rows] * (k + 1) + fragment[rows], weights=w[rows],
                        minlength=(c + 1) * (k + 1)).reshape(c + 1, k + 1)
    largest = np.argmax(piece, axis=1)
    out[rows[fragment[rows] != largest[out[rows]]]] = 0
    return out

