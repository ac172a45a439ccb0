"""Network inputs shared by the runtime pipeline and training (one source of truth).

The paper feeds each point as (shifted xyz, normalised location). We scale the shifted xyz by
the part radius (d_max) so one network serves parts of any size, and we cut the scene into
spatially coherent blocks (not the reference code's random subsamples) so every block keeps the
local density the network was trained on. Neighbourhoods are computed once per block with a
KD-tree on xyz and passed to the network, instead of dense N x N distances in every EdgeConv.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

FEATURE_NAMES = ("x_shift_r", "y_shift_r", "z_shift_r", "nx", "ny", "nz")
NUM_FEATURES = len(FEATURE_NAMES)
# A model trained with surface normals (fpcc train --normals) takes three more columns: the unit
# normal of the plane through each point's NORMAL_NEIGHBOURS nearest, facing the camera
NORMAL_NAMES = ("normal_x", "normal_y", "normal_z")
FEATURE_NAMES_WITH_NORMALS = FEATURE_NAMES + NORMAL_NAMES
NORMAL_NEIGHBOURS = 8   # the first columns of the kNN graph: the nearest (knn_near of a dilated one)


def feature_names(normals: bool) -> tuple[str, ...]:
    """The input columns of a network with or without surface normals."""
    return FEATURE_NAMES_WITH_NORMALS if normals else FEATURE_NAMES


def takes_normals(num_features: int) -> bool:
    """Whether a network with this many input columns takes surface normals."""
    return num_features == len(FEATURE_NAMES_WITH_NORMALS)


def voxel_downsample(xyz: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """One representative input point per occupied voxel.

    Returns ``(keep, inverse)``: ``xyz[keep]`` are the representatives (real points, so the
    network sees measured geometry) and ``inverse[i]`` is the row of ``keep`` whose voxel holds
    input point ``i`` -- the index used to carry labels back to every input point.

    The representative of a voxel is its first input point, voxels in ascending key order (what
    ``np.unique(keys, return_index=True, return_inverse=True)`` gives). When the voxel grid of
    the cloud's bounding box is small (a camera view: ~0.5M cells for 300k points) the first
    points and ranks come from a table over the grid instead of sorting the keys.
    """
    n = len(xyz)
    if voxel_size <= 0 or n == 0:
        return np.arange(n), np.arange(n)
    cols = np.asarray(xyz).T  # per-axis passes over contiguous rows: the same arithmetic, faster
    if not cols.flags.c_contiguous:
        cols = cols.copy()
    cells = np.empty((3, n), dtype=np.int64)
    for d in range(3):
        step = cols[d] - cols[d].min()
        step /= voxel_size
        cells[d] = np.floor(step, out=step)
    dims = cells.max(axis=1) + 1
    keys = (cells[0] * dims[1] + cells[1]) * dims[2] + cells[2]
    total = int(dims[0]) * int(dims[1]) * int(dims[2])  # Python int: never overflows
    if total >= 2**62:  # keys would overflow int64 (kilometre extents at mm voxels): sort rows
        _, keep, inverse = np.unique(cells.T, axis=0, return_index=True, return_inverse=True)
        return keep, inverse.reshape(-1)
    if total > DENSE_VOXEL_CELLS_PER_POINT * n + 4096:  # sparse outliers: sort instead
        _, keep, inverse = np.unique(keys, return_index=True, return_inverse=True)
        return keep, inverse.reshape(-1)
    small = np.int32 if n < 2**31 - 1 else np.int64  # halves the table (fresh pages cost)
    first = np.full(total, n, dtype=small)
    np.minimum.at(first, keys, np.arange(n, dtype=small))
    occupied = np.flatnonzero(first < n)             # the unique keys, ascending
    rank = np.empty(total, dtype=small)              # read only where occupied
    rank[occupied] = np.arange(len(occupied), dtype=small)
    return first[occupied].astype(np.int64), rank[keys].astype(np.int64)


# voxel_downsample's table is used while the grid has at most this many cells per input point
DENSE_VOXEL_CELLS_PER_POINT = 16


def spatial_blocks(xyz: np.ndarray, block_size: int) -> list[np.ndarray]:
    """Split points into disjoint, spatially coherent blocks of at most ``block_size``.

    Recursive median cuts along the longest axis: blocks are compact tiles of similar size, so
    the network's global max-pool sees a neighbourhood of parts, as in training.
    """
    pending = [np.arange(len(xyz))]
    blocks: list[np.ndarray] = []
    while pending:
        idx = pending.pop()
        if len(idx) <= block_size:
            if len(idx):
                blocks.append(idx)
            continue
        low, high = _cut_longest_axis(xyz, idx, len(idx) // 2)
        pending.append(high)
        pending.append(low)
    return blocks


def column_bounds(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column (min, max) of an (n, 3) array. ``xyz.min(axis=0)`` reduces such an array a
    row of three at a time, ~8-25x slower than a pass per column (2,048 rows: 80 vs 10 us; the
    block splits, block features and halo boxes of the bench's 20-part bin: 4.7 -> 2.4 ms)."""
    columns = range(xyz.shape[1])
    return (np.array([xyz[:, d].min() for d in columns]),
            np.array([xyz[:, d].max() for d in columns]))


def tile_order(xyz: np.ndarray, per_tile: int) -> np.ndarray:
    """A permutation of the rows that groups them into square tiles of about ``per_tile``
    points over the cloud's two widest axes (rows keep their order within a tile).

    Consecutive rows of a camera cloud are image rows: a run of a few hundred of them is a strip
    across the whole bin, whose bounding box a small sphere anywhere along it reaches; a tile of
    as many rows is compact. (The tile keys are 16-bit where they fit: numpy's stable sort is a
    radix sort for those.)
    """
    n = len(xyz)
    if n == 0:
        return np.arange(0)
    cols = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64).T)
    lo, hi = cols.min(axis=1), cols.max(axis=1)
    wide = np.argsort(hi - lo)[1:]                       # the two widest axes
    side = float(np.sqrt((hi - lo)[wide].prod() * per_tile / n))
    if not side > 0:                                     # a point or a line: keep the order
        return np.arange(n)
    a, b = (((cols[axis] - lo[axis]) * (1.0 / side)).astype(np.int64) for axis in wide)
    key = a * (int(b.max()) + 1) + b
    return np.argsort(key.astype(np.int16) if key.max() < 2**15 else key, kind="stable")


def _cut_longest_axis(xyz: np.ndarray, idx: np.ndarray, at: int) -> tuple[np.ndarray, np.ndarray]:
    """``idx`` split into its ``at`` lowest points along the axis of largest extent, and the rest."""
    pts = xyz[idx]
    lo, hi = column_bounds(pts)
    axis = int(np.argmax(hi - lo))
    order = np.argsort(pts[:, axis], kind="stable")
    return idx[order[:at]], idx[order[at:]]


def balanced_blocks(xyz: np.ndarray, block_size: int) -> list[np.ndarray]:
    """Like :func:`spatial_blocks`, but ceil(n / block_size) blocks of nearly equal size.

    Halving stops only below ``block_size``, so 8240 points become 8 blocks of 1030; here they
    become 5 of 1648 (sizes stay in [block_size/2, block_size], the range halving gives too).
    At runtime every block carries a halo of context, so fewer blocks means fewer halo points
    through the network (about 20% fewer on cluttered 640x480 bins). Cuts along the longest
    axis, each at the fraction of points the blocks on either side need.
    """
    n = len(xyz)
    pending = [(np.arange(n), -(-n // block_size))]
    blocks: list[np.ndarray] = []
    while pending:
        idx, parts = pending.pop()
        if parts <= 1:
            if len(idx):
                blocks.append(idx)
            continue
        left = parts // 2
        low, high = _cut_longest_axis(xyz, idx, (len(idx) * left) // parts)
        pending.append((high, parts - left))
        pending.append((low, left))
    return blocks


def block_features(xyz: np.ndarray, part_radius: float,
                   normals_knn: np.ndarray | None = None) -> np.ndarray:
    """(n, 6) float32: xyz shifted to the block minimum and divided by the part radius, then the
    location normalised to [0, 1] over the block (paper eq. 1 plus the normalised location).
    With ``normals_knn`` (the block's (n, k) kNN graph, nearest first) (n, 9): the
    :func:`surface_normals` as three more columns, for models trained with them."""
    lo, hi = column_bounds(xyz)
    shifted = xyz - lo
    extent = np.maximum(hi - lo, 1e-9)   # = shifted.max(axis=0): rounding is monotonic
    columns = [shifted / part_radius, shifted / extent]
    if normals_knn is not None:
        columns.append(surface_normals(xyz, normals_knn))
    return np.concatenate(columns, axis=1).astype(np.float32)


def block_inputs(xyz: np.ndarray, part_radius: float, k: int, normals: bool = False,
                 near: int = 0, reach: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One block's network inputs, (features, knn), from its own kNN graph (:func:`knn_graph`),
    as training and the model checks build them (the node shares one KD-tree across blocks)."""
    knn = knn_graph(xyz, k, near=near, reach=reach)
    return block_features(xyz, part_radius, knn if normals else None), knn


def surface_normals(xyz: np.ndarray, knn: np.ndarray) -> np.ndarray:
    """(n, 3) unit normals: the direction of least spread of each point's first
    :data:`NORMAL_NEIGHBOURS` neighbours in ``knn`` (itself included), turned to face a camera
    looking along +z (the network's frame: pipeline.to_camera), so the sign carries meaning.

    Touching parts meet at creases, where the normal turns sharply while xyz runs on smoothly;
    xyz alone leaves the network to infer that from its neighbourhoods. The least eigenvector
    of each 3x3 scatter matrix comes in closed form (:func:`_least_eigenvectors`, 0.5 ms for
    a 3,000-point block where numpy's batched ``eigh`` took 2.9; 1.2 ms for the whole call).
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3))
    columns = np.ascontiguousarray(pts.T)
    near = knn[:, :NORMAL_NEIGHBOURS]
    x, y, z = (np.take(c, near) for c in columns)            # (n, m) each
    x -= x.mean(axis=1, keepdims=True)
    y -= y.mean(axis=1, keepdims=True)
    z -= z.mean(axis=1, keepdims=True)
    normals = _least_eigenvectors((x * x).sum(1), (y * y).sum(1), (z * z).sum(1),
                                  (x * y).sum(1), (x * z).sum(1), (y * z).sum(1))
    normals *= np.where(normals[:, 2] > 0, -1.0, 1.0)[:, None]   # facing the camera
    return normals


def _least_eigenvectors(xx: np.ndarray, yy: np.ndarray, zz: np.ndarray, xy: np.ndarray,
                        xz: np.ndarray, yz: np.ndarray) -> np.ndarray:
    """(n, 3) unit eigenvectors of the least eigenvalue of symmetric 3x3 matrices given by
    their six entries: the eigenvalue from the trigonometric solution of the characteristic
    cubic, the vector as the longest cross product of two rows of (S - lambda I). A matrix
    without a unique least direction (a point alone, a line) gets (0, 0, 1)."""
    q = (xx + yy + zz) / 3.0
    off = xy * xy + xz * xz + yz * yz
    p = np.sqrt(((xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    a, d, f = (xx - q) / safe, (yy - q) / safe, (zz - q) / safe
    b, c, e = xy / safe, xz / safe, yz / safe
    half_det = 0.5 * (a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c))
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    least = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    u, v, w = xx - least, yy - least, zz - least     # rows (u xy xz), (xy v yz), (xz yz w)
    crosses = ((xy * yz - xz * v, xz * xy - u * yz, u * v - xy * xy),     # row 0 x row 1
               (xy * w - xz * yz, xz * xz - u * w, u * yz - xy * xz),     # row 0 x row 2
               (v * w - yz * yz, yz * xz - xy * w, xy * yz - v * xz))     # row 1 x row 2
    lengths = [cx * cx + cy * cy + cz * cz for cx, cy, cz in crosses]
    pick = np.argmax(np.stack(lengths), axis=0)
    out = np.stack([np.choose(pick, [c[i] for c in crosses]) for i in range(3)], axis=1)
    norm = np.sqrt(np.choose(pick, lengths))
    unique = norm > 1e-9 * p * p        # else: no unique least direction (or p = 0)
    out[unique] /= norm[unique, None]
    out[~unique] = (0.0, 0.0, 1.0)
    return out


def neighbour_columns(k: int, near: int, reach: int) -> np.ndarray:
    """Which of the ``reach`` nearest neighbours form a k-wide dilated neighbourhood: the
    ``near`` closest (local shape), then ``k - near`` spread evenly over the rest (context).

    All three EdgeConv layers share one xyz graph (no feature-space kNN): with the k nearest
    alone, three hops reach ~0.7 part radii at the default voxel, too little to tell where a
    part's center is; the spread-out edges let three hops cover the whole part.
    """
    if reach <= k or near >= k:
        return np.arange(k)
    far = np.linspace(near, reach - 1, k - near).round().astype(np.int64)
    return np.concatenate([np.arange(near), far])


def select_neighbours(idx: np.ndarray, k: int, near: int, reach: int) -> np.ndarray:
    """A (n, reach) nearest-first neighbour table cut to the (n, k) dilated neighbourhood."""
    return idx if idx.shape[1] == k else np.ascontiguousarray(idx[:, neighbour_columns(k, near, reach)])


def knn_graph(xyz: np.ndarray, k: int, workers: int = 1, near: int = 0,
              reach: int = 0) -> np.ndarray:
    """(n, k) int64 indices of each point's k nearest neighbours in 3D, itself first.

    Blocks smaller than k repeat their farthest neighbour so the graph keeps a fixed width.
    ``workers`` > 1 (or -1: all CPUs) splits the queries over threads; every query is answered
    alone, so the result does not depend on it.
    """
    if reach > k:  # dilated: the reach nearest, then the card's column selection
        return select_neighbours(knn_graph(xyz, reach, workers), k, near, reach)
    n = len(xyz)
    kk = min(k, n)
    _, idx = cKDTree(xyz).query(xyz, k=kk, workers=workers)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, kk)
    if kk < k:
        idx = np.concatenate([idx, np.repeat(idx[:, -1:], k - kk, axis=1)], axis=1)
    return idx


def block_knn_graphs(xyz: np.ndarray, blocks: list[np.ndarray], k: int,
                     workers: int = 1) -> list[np.ndarray]:
    """``knn_graph(xyz[b], k)`` for every block ``b`` (any subset of rows, e.g. a core plus its
    halo), from one KD-tree over all the points instead of one per block.

    A point whose k nearest neighbours in ``xyz`` all lie in its block (and whose k-th is not
    tied with the (k+1)-th) has the same k nearest neighbours in the block as in the whole cloud:
    the block is a subset holding all of them. Only the rest (points near a block's edge with
    neighbours beyond it) are queried in the block's own tree, as knn_graph does. Rows hold the
    same neighbours at the same distances as knn_graph's; neighbours at exactly equal distances
    may come in another order. The network takes a max over each row, so its output does not
    depend on that order. With halos around blocks every point lies in ~2.5 blocks: this queries
    each point about once (measured on a 40-part bin: 4,763 of 18,483 rows re-queried; the
    earlier test, "the k-th neighbour is nearer than the box's faces", re-queried 5,873).
    """
    n = len(xyz)
    graphs: list[np.ndarray] = []
    if n <= k:
        return [knn_graph(xyz[b], k, workers) for b in blocks]
    dist, idx = cKDTree(xyz).query(xyz, k=k + 1, workers=workers)
    unique = dist[:, k - 1] < dist[:, k]            # no tie at the k-th neighbour
    local = np.full(n, -1, dtype=np.int64)
    for block in blocks:
        m = len(block)
        if m <= k:
            graphs.append(knn_graph(xyz[block], k, workers))
            continue
        pts = np.take(xyz, block, axis=0)
        local[block] = np.arange(m)
        graph = np.take(local, np.take(idx, block, axis=0)[:, :k])  # -1: outside the block
        inner = unique[block] & (graph.min(axis=1) >= 0)
        rest = np.flatnonzero(~inner)
        if len(rest):
            _, near = cKDTree(pts).query(pts[rest], k=k, workers=workers)
            graph[rest] = np.asarray(near, dtype=np.int64).reshape(len(rest), k)
        local[block] = -1
        graphs.append(graph)
    return graphs


def dominant_plane(xyz: np.ndarray, tolerance: float, min_fraction: float = 0.2,
                   hypotheses: int = 96, sample: int = 4096, seed: int = 0) -> np.ndarray:
    """Boolean mask of the points on the largest plane, or all False if it is smaller than
    ``min_fraction`` of the points.

    In a bin view the floor around the tote is most of the cloud and carries no instance; taking
    it out before the network (at runtime and in training alike) cuts the work by half or more.
    A pile that hides the floor leaves no large plane and nothing is removed. Vectorised RANSAC
    with a fixed seed (same cloud, same answer), refined by a least-squares fit to the inliers.
    """
    n = len(xyz)
    none = np.zeros(n, dtype=bool)
    if n < 3:
        return none
    rng = np.random.default_rng(seed)
    sub = xyz[rng.choice(n, min(n, sample), replace=False)]
    tri = sub[rng.integers(0, len(sub), (hypotheses, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-12
    if not ok.any():
        return none
    normals = normals[ok] / length[ok, None]
    offsets = -(normals * tri[ok, 0]).sum(axis=1)
    support = (np.abs(sub @ normals.T + offsets) < tolerance).sum(axis=0)
    best = int(np.argmax(support))
    inliers = sub[np.abs(sub @ normals[best] + offsets[best]) < tolerance]
    if len(inliers) >= 3:  # least-squares refinement
        centroid = inliers.mean(axis=0)
        normal = np.linalg.svd(inliers - centroid, full_matrices=False)[2][-1]
        offset = -float(normal @ centroid)
    else:
        normal, offset = normals[best], offsets[best]
    mask = np.abs(xyz @ normal + offset) < tolerance
    return mask if mask.mean() >= min_fraction else none


def plane_tolerance(part_radius: float) -> float:
    """Inlier distance for :func:`dominant_plane`: above depth noise, below a part's thickness."""
    return float(np.clip(0.1 * part_radius, 0.004, 0.012))
