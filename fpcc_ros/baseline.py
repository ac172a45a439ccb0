"""The classical baselines users compare FPCC against: plane removal + Euclidean clustering or
DBSCAN.

This is the usual learning-free bin-picking recipe (PCL's SACSegmentation followed by
EuclideanClusterExtraction with a minimum cluster size, or scikit-learn's DBSCAN): crop, remove
the tote's floor and walls, then call every connected blob of points one part (Euclidean), or
every blob of dense points (DBSCAN: a thin bridge of sparse points -- flying pixels between two
parts, a grazing edge -- no longer joins them). Both drop clusters under a minimum size. They
work when parts lie apart and merge parts that touch -- the case FPCC is for. Pure numpy/scipy
and no ground truth anywhere, so the comparison is honest.

Plane rule (why a plane is removed, and when not). In a bin the dominant plane is the floor
(the tote's or the one it stands on) -- or, when a pile hides the floor, nothing real: a slice
through the pile. So planes are searched for one at a time by RANSAC (largest first) and:

1. the first plane is the floor only if its largest *connected* piece of inliers holds at least
   ``floor_share`` (8 %) of all points. Points are counted after a voxel grid at the plane
   tolerance, i.e. by area, not by pixel density. A floor is one large connected sheet; a layer
   of separate flat part faces at one height is many small pieces. No floor, no plane removed.
2. after a floor, up to four walls: planes perpendicular to the floor (within ~17 degrees) whose
   largest piece holds at least ``wall_share`` (2 %) of all points. Planes at other angles are
   set aside (searched past, not removed): a second plane parallel to the floor is, in practice,
   often the top faces of flat parts lying on it (on synthetic totes of flanges, also removing
   parallel planes took 39 % of the part points; on washers, 57 % of such a plane's points were
   washer points), and an oblique one is a slice through the pile. The price: a second floor
   level (a tote's bottom above the larger floor it stands on) stays in.
   The search stops at the first plane below ``wall_share`` (RANSAC returns the largest plane, so
   every later one would be smaller) or after ``max_planes`` planes or 8 candidates.

A removed plane takes every point within ``plane_tolerance`` of it, including the bottom edge of
parts lying on the floor or leaning on a wall. Whatever background survives (tote rim, floor
beyond the tote, noise) is clustered like everything else -- as it would be in a real cell.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from fpcc_ros.dbscan import dbscan, radius_pairs
from fpcc_ros.features import voxel_downsample

FLOOR_SHARE = 0.08          # the floor is at least this share of the scene's area
WALL_SHARE = 0.02           # a tote wall at least this share
MAX_PLANES = 5              # floor + four walls
MAX_CANDIDATES = 8          # planes looked at, including those set aside
WALL_MAX_COS = 0.3          # |cos| between a wall's normal and the floor's (>= ~73 degrees)
RANSAC_HYPOTHESES = 512
RANSAC_SAMPLE = 2048        # hypotheses are scored on this many points, the winner on all
VOXEL_PER_TOLERANCE = 1 / 3  # voxel <= tol/3 keeps face-adjacent voxels' points within tol

Roi = tuple[Sequence[float], Sequence[float]]


@dataclass(frozen=True)
class Plane:
    """``normal . p + offset = 0`` with a unit normal; ``support`` = points in its largest piece."""

    normal: np.ndarray
    offset: float
    support: int

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        return np.abs(xyz @ self.normal + self.offset)


def default_plane_tolerance(part_radius: float) -> float:
    """Band around a floor/wall that is removed: 5 % of d_max, kept within 2-10 mm (sensor noise
    at bin distances is ~1-2 mm; a wider band would eat the parts lying on the floor)."""
    return float(np.clip(0.05 * part_radius, 0.002, 0.01))


def valid_mask(xyz: np.ndarray, roi: Roi | None = None) -> np.ndarray:
    """Finite points, inside the ``(min_xyz, max_xyz)`` box when one is given."""
    valid = np.isfinite(xyz).all(axis=1)
    if roi is not None:
        lo, hi = (np.asarray(c, dtype=np.float64) for c in roi)
        with np.errstate(invalid="ignore"):
            valid &= ((xyz >= lo) & (xyz <= hi)).all(axis=1)
    return valid


def find_planes(xyz: np.ndarray, tolerance: float, floor_share: float = FLOOR_SHARE,
                wall_share: float = WALL_SHARE, max_planes: int = MAX_PLANES,
                seed: int = 0) -> list[Plane]:
    """Floor, then walls, among finite points, by the rule in the module docstring."""
    keep, _ = voxel_downsample(xyz, tolerance)
    pts = xyz[keep].astype(np.float64)
    total = len(pts)
    rng = np.random.default_rng(seed)
    planes: list[Plane] = []
    for _ in range(MAX_CANDIDATES):
        if len(planes) >= max_planes or len(pts) < 3:
            break
        plane = _ransac_plane(pts, tolerance, rng)
        if plane is None:
            break
        on = plane.distance(pts) <= tolerance
        support = _largest_piece(pts[on], tolerance)
        if support < (wall_share if planes else floor_share) * total:
            break
        pts = pts[~on]
        if not planes or abs(float(plane.normal @ planes[0].normal)) <= WALL_MAX_COS:
            planes.append(Plane(plane.normal, plane.offset, support))
    return planes


def off_planes(xyz: np.ndarray, planes: Sequence[Plane], tolerance: float) -> np.ndarray:
    """True for points farther than ``tolerance`` from every plane."""
    off = np.ones(len(xyz), bool)
    for plane in planes:
        off &= plane.distance(xyz) > tolerance
    return off


def foreground_mask(xyz: np.ndarray, plane_tolerance: float, roi: Roi | None = None,
                    max_planes: int = MAX_PLANES, seed: int = 0) -> tuple[np.ndarray, list[Plane]]:
    """Points left for clustering: finite, in the ROI, off the floor and walls. Independent of
    the clustering tolerance, so a tolerance sweep computes it once."""
    xyz = np.asarray(xyz, dtype=np.float64)
    mask = valid_mask(xyz, roi)
    idx = np.flatnonzero(mask)
    planes = find_planes(xyz[idx], plane_tolerance, max_planes=max_planes, seed=seed) if len(idx) else []
    mask[idx] = off_planes(xyz[idx], planes, plane_tolerance)
    return mask, planes


def cluster_foreground(xyz: np.ndarray, foreground: np.ndarray, tolerance: float, min_points: int,
                       voxel_size: float | None = None) -> np.ndarray:
    """Connected components of the radius-``tolerance`` graph over the foreground points.

    Clustering runs on voxel representatives (``voxel_size``; None = tolerance/3, 0 = off) and the
    labels are carried back to every point. Representatives are real points, so downsampling can
    only drop links, never add one: a gap wider than ``tolerance`` always separates, a slightly
    narrower one may too once voxels are coarser than the scan (the sweep absorbs this). Clusters
    with fewer than ``min_points`` input points get 0; the rest are numbered 1..K by decreasing
    size. Returns (N,) uint32.
    """
    labels = np.zeros(len(xyz), np.uint32)
    idx = np.flatnonzero(foreground)
    if len(idx) == 0:
        return labels
    pts = np.asarray(xyz, dtype=np.float64)[idx]
    voxel = tolerance * VOXEL_PER_TOLERANCE if voxel_size is None else voxel_size
    keep, inverse = voxel_downsample(pts, voxel)
    components = _radius_components(pts[keep], tolerance)[inverse]
    sizes = np.bincount(components)
    order = np.argsort(-sizes, kind="stable")
    new_id = np.zeros(len(sizes), np.uint32)
    kept = order[sizes[order] >= max(int(min_points), 1)]
    new_id[kept] = np.arange(1, len(kept) + 1, dtype=np.uint32)
    labels[idx] = new_id[components]
    return labels


def dbscan_foreground(xyz: np.ndarray, foreground: np.ndarray, eps: float, min_samples: int,
                      min_cluster_size: int, voxel_size: float | None = None) -> np.ndarray:
    """DBSCAN (fpcc_ros.dbscan) over the foreground points: (N,) uint32 labels, 0 = none.

    Runs on voxel representatives like :func:`cluster_foreground` (``voxel_size`` None = eps/3,
    0 = off), each weighted by the input points it stands for, so ``min_samples`` and
    ``min_cluster_size`` count input points (a sweep over ``min_samples`` calls
    :func:`representative_graph` once per eps and :func:`fpcc_ros.dbscan.dbscan` per setting).
    """
    labels = np.zeros(len(xyz), np.uint32)
    idx = np.flatnonzero(foreground)
    if len(idx) == 0:
        return labels
    reps, weights, inverse, pairs = representative_graph(xyz, idx, eps, voxel_size)
    rep_labels = dbscan(reps, eps, min_samples, min_cluster_size, weights=weights, pairs=pairs)
    labels[idx] = rep_labels[inverse].astype(np.uint32)
    return labels


def representative_graph(xyz: np.ndarray, idx: np.ndarray, eps: float,
                         voxel_size: float | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Voxel representatives of ``xyz[idx]`` (voxel None = eps/3): ``(reps, weights, inverse,
    pairs)`` -- the input points each stands for, the representative of every ``idx`` row, and
    the radius-``eps`` pairs between representatives."""
    pts = np.asarray(xyz, dtype=np.float64)[idx]
    voxel = eps * VOXEL_PER_TOLERANCE if voxel_size is None else voxel_size
    keep, inverse = voxel_downsample(pts, voxel)
    weights = np.bincount(inverse, minlength=len(keep)).astype(np.float64)
    reps = pts[keep]
    return reps, weights, inverse, radius_pairs(reps, eps)


def dbscan_clusters(xyz: np.ndarray, eps: float, min_samples: int, min_cluster_size: int,
                    voxel_size: float | None = None, roi: Roi | None = None, *,
                    plane_tolerance: float = 0.005, max_planes: int = MAX_PLANES,
                    seed: int = 0) -> np.ndarray:
    """The DBSCAN baseline on one cloud: (N, 3) with NaNs allowed -> (N,) uint32 labels, 0 = none.

    The same crop and floor/wall removal as :func:`euclidean_clusters`, then
    :func:`dbscan_foreground`. ``min_samples`` counts the point itself (as scikit-learn does).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    mask, _ = foreground_mask(xyz, plane_tolerance, roi, max_planes, seed)
    return dbscan_foreground(xyz, mask, eps, min_samples, min_cluster_size, voxel_size)


def euclidean_clusters(xyz: np.ndarray, tolerance: float, min_points: int, voxel_size: float | None,
                       roi: Roi | None = None, *, plane_tolerance: float = 0.005,
                       max_planes: int = MAX_PLANES, seed: int = 0) -> np.ndarray:
    """The Euclidean baseline on one cloud: (N, 3), NaNs allowed -> (N,) uint32 labels, 0 = none.

    ``min_points`` is the minimum cluster size (input points); ``roi`` is ``(min_xyz, max_xyz)``
    or None; ``voxel_size`` None means tolerance/3;
    ``max_planes`` 0 turns plane removal off.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    mask, _ = foreground_mask(xyz, plane_tolerance, roi, max_planes, seed)
    return cluster_foreground(xyz, mask, tolerance, min_points, voxel_size)


def _radius_components(pts: np.ndarray, radius: float) -> np.ndarray:
    """Component id per point of the graph linking points closer than ``radius``."""
    n = len(pts)
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, components = connected_components(graph, directed=False)
    return components


def _largest_piece(pts: np.ndarray, tolerance: float) -> int:
    """Points in the largest connected piece of a plane's inliers (voxel representatives at
    ``tolerance``; linked within 3 grid steps, or 3 typical spacings where the scan is sparser)."""
    if len(pts) < 2:
        return len(pts)
    spacing, _ = cKDTree(pts).query(pts, k=2)
    link = 3.0 * max(tolerance, float(np.median(spacing[:, 1])))
    return int(np.bincount(_radius_components(pts, link)).max())


def _ransac_plane(pts: np.ndarray, tolerance: float, rng: np.random.Generator) -> Plane | None:
    """The plane with most inliers: hypotheses scored together on a sample, refined by SVD.

    Each hypothesis is a seed point and two of its 32 nearest neighbours *within the sample*, so
    triangles span a tenth of the scene or so: mostly on one surface, wide enough for a good normal.
    """
    sample = pts[rng.choice(len(pts), min(len(pts), RANSAC_SAMPLE), replace=False)]
    k = min(32, len(sample) - 1)
    if k < 2:
        return None
    _, nbr = cKDTree(sample).query(sample, k=k + 1)
    seeds = rng.integers(0, len(sample), RANSAC_HYPOTHESES)
    first = rng.integers(1, k + 1, RANSAC_HYPOTHESES)
    second = 1 + (first - 1 + rng.integers(1, k, RANSAC_HYPOTHESES)) % k  # != first
    a = sample[seeds]
    normal = np.cross(sample[nbr[seeds, first]] - a, sample[nbr[seeds, second]] - a)
    length = np.linalg.norm(normal, axis=1)
    ok = length > 1e-12
    if not ok.any():
        return None
    normal = normal[ok] / length[ok, None]
    offset = -(normal * a[ok]).sum(axis=1)
    score = (np.abs(sample @ normal.T + offset) <= tolerance).sum(axis=0)
    best = int(np.argmax(score))
    plane = Plane(normal[best], float(offset[best]), 0)
    for _ in range(2):  # least-squares refit on the inliers of all points
        inliers = pts[plane.distance(pts) <= tolerance]
        if len(inliers) < 3:
            break
        center = inliers.mean(axis=0)
        n = np.linalg.svd(inliers - center, full_matrices=False)[2][-1]
        plane = Plane(n, float(-n @ center), 0)
    return plane
