"""Geometric fragments for the connected clustering: the pieces connectivity alone separates.

DBSCAN's semantics (a *core* point has enough neighbours within ``eps``; fragments are connected
core points; a border point joins a core neighbour; the rest is noise), two ways:

* :func:`pixel_fragments`, for an organized cloud (a camera's ``height x width`` image): two
  neighbouring pixels (right, down) are *linked* when both are measured, off the floor and
  within ``eps`` in 3D; between two measured but unlinked neighbours (a jump: an occlusion
  edge, or a gap between parts) the deeper pixel is cut. A core pixel has a link and is not
  cut, so no two adjacent core pixels are ever unlinked, and the fragments are the
  4-connected components of the core mask: one ``scipy.ndimage.label`` over the image. On the
  640x480 validation piles it takes ~5 ms where the KD-tree radius graph of the grid DBSCAN
  took 60-100 ms (AMD EPYC, 2 cores), at equal or better F1.
* in both directions a pixel on a *concave crease* (:func:`concave_creases`: where the surface
  folds away from the camera more sharply than the ``crease`` curvature, the card's
  ``fragment_crease``) is cut too. Two parts that touch in a pile meet at such a valley; xyz
  distances alone link them into one fragment. Convex folds (a shaft's top, an edge facing the
  camera) stay linked. A fragment that fits in one part before these cuts keeps its creases
  (``whole_diagonal``): its valleys are the part's own (a gear shaft's step, a flange's bore),
  and cutting them only made pieces for the centers to join.
* an unorganized cloud has no image: the pipeline runs :func:`fpcc_ros.dbscan.dbscan` on a
  grid of half ``eps`` instead (``Pipeline._fragments``).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage


# neighbouring pixels link within this many eps: one surface's pixels lie farther apart than
# the points in a DBSCAN ball (9 mm links vs the grid's 6 mm eps, 6 piles each, shipped model:
# F1 0.565 gear shaft / 0.672 ring screw vs the grid's 0.541 / 0.671; at 6 mm 0.596 / 0.561)
PIXEL_LINK = 1.5
# A pixel whose surface curves away from the camera (concave) by more than this many 1/m along
# the image rows or columns is a crease: the valley where two touching parts meet. The shipped
# card's `fragment_crease`; the value was chosen on piles that are not the README's validation
# piles (8 IPA gear-shaft and 8 ring-screw piles, seeds 950000 / 960000, and the 28 built-in
# validation piles), shipped model at its card (visible F1 gear / ring / mean part F1 built-in):
# off 0.608 / 0.618 / 0.589; 90: 0.633 / 0.595; 120: 0.637 / 0.616 / 0.602; 150: 0.624 / 0.620
# / 0.593; 180: 0.611 / 0.622; 250 cuts nothing. With ground truth deciding which fragments are
# one part, the fragments at 120 could score 0.92 / 0.92 on those IPA piles (0.87 / 0.82 uncut).
CREASE_CURVATURE = 120.0
# curvature is measured between pixels this many apart, on xyz smoothed over 3 x 3 pixels: at
# 1-2 mm pixel pitch a shorter baseline measures the sensor's noise, a longer one blurs the valley
CREASE_STEP = 2
CREASE_SMOOTH = 3
# A fragment's extent, to tell whether it fits in a part, from every 2nd pixel row and column:
# off by at most two pixel pitches (2-4 mm against parts of tens of mm), a quarter of the work
WHOLE_STRIDE = 2
# pixels from a crease to the farthest pixel its measurement reads: the pair's half distance
# (CREASE_STEP), the tangent's (CREASE_STEP) and the smoothing window's radius
CREASE_REACH = 2 * CREASE_STEP + CREASE_SMOOTH // 2


def pixel_fragments(xyz: np.ndarray, pixels: np.ndarray, image_shape: tuple[int, int],
                    eps: float, depth_axis: int = 2, depth_sign: float = 1.0,
                    crease: float = 0.0, whole_diagonal: float = 0.0) -> np.ndarray:
    """Fragment ids 1..K (0 = noise) of the points at flat pixel indices ``pixels`` of an
    organized cloud ``xyz`` (``height * width`` rows, row-major, as PointCloud2 lays it out).

    Pixels not in ``pixels`` (no return, outside the ROI, on the floor) link to nothing; pixels
    on a concave crease sharper than ``crease`` (1/m, 0 = off) are cut like the deeper side of a
    jump. A fragment whose bounding-box diagonal is at most ``whole_diagonal`` (m) before the
    crease cuts keeps its creases: it fits in one part, so its valleys are the part's own.
    """
    height, width = image_shape
    member = np.zeros(height * width, bool)
    member[pixels] = True
    member = member.reshape(height, width)
    # x, y, z as contiguous planes: the neighbour differences then run over contiguous rows
    # (1.6 ms for the right neighbours from the strided columns, 0.7 ms from planes)
    planes = np.ascontiguousarray(np.asarray(xyz, np.float32).T).reshape(3, height, width)
    depth = planes[depth_axis] * np.float32(depth_sign)
    limit = np.float32(eps) ** 2
    # per direction (right, down): neighbours linked within eps; at a jump between measured
    # neighbours the deeper pixel is cut from the core, so the nearer surface keeps its edge
    # and no two adjacent core pixels are ever unlinked
    cut = np.zeros((height, width), bool)
    right, down = (_linked(planes, member, depth, limit, cut, before, after)
                   for before, after in ((np.s_[:, :-1], np.s_[:, 1:]),
                                         (np.s_[:-1, :], np.s_[1:, :])))
    linked = np.zeros((height, width), bool)
    linked[:, :-1] |= right
    linked[:, 1:] |= right
    linked[:-1] |= down
    linked[1:] |= down
    core, _ = ndimage.label(linked & ~cut)
    if crease > 0:
        core = _cut_at_creases(core, planes, member, crease, eps, depth_axis, depth_sign,
                               whole_diagonal)
    fragment = core.reshape(-1)
    # border pixels (linked, but cut at a jump): the fragment of a linked core neighbour
    border = np.flatnonzero(linked.reshape(-1) & (fragment == 0))
    fragment[border] = _border_fragments(fragment, right, down, border, width)
    return fragment[pixels]


def _cut_at_creases(core: np.ndarray, planes: np.ndarray, member: np.ndarray,
                    crease: float, eps: float, depth_axis: int, depth_sign: float,
                    whole_diagonal: float) -> np.ndarray:
    """``core`` (labels of the core components) relabelled after cutting the components larger
    than a box of diagonal ``whole_diagonal`` (all of them at 0) along their concave creases.
    The creases are measured only in the box around those components (with the filters'
    reach as margin): on a sparse scene often nothing, on a full tote most of the image."""
    large = np.ones(int(core.max()) + 1, bool)
    large[0] = False
    if whole_diagonal > 0:
        components, diagonals = _diagonals_on_grid(core, planes, large)
        large[components] = diagonals > whole_diagonal
    in_large = large[core]
    rows, cols = np.flatnonzero(in_large.any(axis=1)), np.flatnonzero(in_large.any(axis=0))
    if len(rows) == 0:
        return core
    m = CREASE_REACH
    box = np.s_[max(rows[0] - m, 0):rows[-1] + m + 1, max(cols[0] - m, 0):cols[-1] + m + 1]
    creased = np.zeros(core.shape, bool)
    creased[box] = concave_creases(planes[(slice(None),) + box], member[box], crease, eps,
                                   depth_axis, depth_sign)
    creased &= in_large
    return ndimage.label((core > 0) & ~creased)[0]


def _diagonals_on_grid(labels: np.ndarray, planes: np.ndarray, wanted: np.ndarray,
                       stride: int = WHOLE_STRIDE) -> tuple[np.ndarray, np.ndarray]:
    """The labels in ``wanted`` (a mask over label ids) that have a pixel on every
    ``stride``-th row and column, and the 3D bounding-box diagonals of those pixels. One
    sort over the sampled pixels (``scipy.ndimage.maximum`` per label took 27-36 ms a plane
    on a 640x480 pile; this ~3 ms for all three)."""
    grid = labels[::stride, ::stride].reshape(-1)
    rows = np.flatnonzero(wanted[grid])
    ids = grid[rows]
    order = np.argsort(ids, kind="stable")
    rows, ids = rows[order], ids[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if len(ids) else rows
    squared = np.zeros(len(starts))
    for plane in planes:
        values = plane[::stride, ::stride].reshape(-1).take(rows)
        if len(starts):
            squared += (np.maximum.reduceat(values, starts)
                        - np.minimum.reduceat(values, starts)).astype(np.float64) ** 2
    return ids[starts], np.sqrt(squared)


def _linked(planes: np.ndarray, member: np.ndarray, depth: np.ndarray, limit: np.float32,
            cut: np.ndarray, before: tuple, after: tuple) -> np.ndarray:
    """Pairs (``before``, ``after``: one pixel and its neighbour) linked within sqrt(limit);
    marks the deeper pixel of each measured but unlinked pair in ``cut``."""
    gap = np.zeros(member[before].shape, np.float32)
    for plane in planes:
        step = plane[after] - plane[before]
        step *= step
        gap += step
    both = member[before] & member[after]
    link = gap <= limit   # NaN compares False
    link &= both
    jump = both & ~link
    deeper = depth[after] > depth[before]
    cut[after] |= jump & deeper
    cut[before] |= jump & ~deeper
    return link


def _border_fragments(core: np.ndarray, right: np.ndarray, down: np.ndarray,
                      border: np.ndarray, width: int) -> np.ndarray:
    """Per border pixel (flat indices), the core fragment of its first linked core neighbour
    in the order right, left, down, up (0 when none); ``core``: the flat core labels, so a
    border pixel never passes its fragment on. Over the few thousand border pixels only."""
    height = len(core) // width
    row, col = np.divmod(border, width)
    right_link, down_link = right.reshape(-1), down.reshape(-1)
    right_at = row * (width - 1) + col   # the link to the right neighbour, in right_link
    got = np.zeros(len(border), core.dtype)
    # (neighbour exists, the links, the link between them, the neighbour's offset)
    for there, links, link_at, offset in ((col < width - 1, right_link, right_at, 1),
                                          (col > 0, right_link, right_at - 1, -1),
                                          (row < height - 1, down_link, border, width),
                                          (row > 0, down_link, border - width, -width)):
        rows = np.flatnonzero(there & (got == 0))
        rows = rows[links[link_at[rows]]]
        got[rows] = core[border[rows] + offset]
    return got


def concave_creases(planes: np.ndarray, member: np.ndarray, curvature: float, link: float,
                    depth_axis: int = 2, depth_sign: float = 1.0,
                    step: int = CREASE_STEP) -> np.ndarray:
    """(height, width) mask of the member pixels where the surface is concave (a valley seen
    from the camera) with a normal curvature above ``curvature`` (1/m) along the rows or columns.

    Normals from central differences ``step`` pixels apart on xyz smoothed over
    :data:`CREASE_SMOOTH` pixels (members only), facing the camera; between the normals n1, n2
    at p1, p2 the surface is concave when (n1 - n2) . (p1 - p2) < 0 (the local convexity test
    of LCCP, Stein et al., CVPR 2014), and that dot over |p1 - p2|^2 is the curvature. A
    difference across a jump (longer than ``2 step link``) measures no surface: never a crease.
    """
    if min(member.shape) <= 4 * step:
        return np.zeros(member.shape, bool)   # too small to hold a pair of normals
    smooth = _smoothed_members(planes, member)
    s = step
    along_row = [_tangent(p[s:-s], s, axis=1) for p in smooth]   # each (h - 2s, w - 2s)
    along_col = [_tangent(p[:, s:-s], s, axis=0) for p in smooth]
    normal = _cross(along_row, along_col)
    length = np.sqrt(_dot(normal, normal))
    jump = np.float32(2 * s * link) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        # facing the camera (against the depth axis); NaN across a jump
        length[normal[depth_axis] * np.float32(depth_sign) > 0] *= -1
        length[(_dot(along_row, along_row) > jump) | (_dot(along_col, along_col) > jump)] = np.nan
        normal = [n / length for n in normal]
        centre = [p[s:-s, s:-s] for p in smooth]
        concave = np.zeros(member.shape, bool)
        # pairs 2 step apart along the rows, then the columns; the crease is their middle pixel
        pairs = ((np.s_[:, :-2 * s], np.s_[:, 2 * s:], np.s_[s:-s, 2 * s:-2 * s]),
                 (np.s_[:-2 * s, :], np.s_[2 * s:, :], np.s_[2 * s:-2 * s, s:-s]))
        for before, after, middle in pairs:
            gap = [c[before] - c[after] for c in centre]
            bend = _dot([n[before] - n[after] for n in normal], gap)
            # concave beyond the curvature: bend / |gap|^2 < -curvature (NaN compares False)
            concave[middle] |= bend < -np.float32(curvature) * _dot(gap, gap)
    return concave & member


def _tangent(plane: np.ndarray, s: int, axis: int) -> np.ndarray:
    """The difference 2 ``s`` pixels across each pixel along ``axis`` (the pixels ``s`` from
    the ends dropped), or twice the one-sided difference where one side is missing (NaN): a
    crease then reaches the end of a valley, where a hole or a jump begins, instead of stopping
    ``s`` pixels short and leaving a bridge between the two parts."""
    def span(start: int, stop: int) -> np.ndarray:
        index = [slice(None), slice(None)]
        index[axis] = slice(start, plane.shape[axis] - 2 * s + stop)
        return plane[tuple(index)]
    before, middle, after = span(0, 0), span(s, s), span(2 * s, 2 * s)
    forward, backward = after - middle, middle - before
    central = forward + backward
    # copyto with a mask: 0.3 ms a plane where gathering the NaN pixels took 2.4
    np.copyto(central, backward * 2, where=np.isnan(forward))
    np.copyto(central, forward * 2, where=np.isnan(backward))
    return central


def _dot(a: list[np.ndarray], b: list[np.ndarray]) -> np.ndarray:
    """Per-pixel dot product of two 3-vectors stored as three planes (faster than summing an
    axis-0 stack: 3 ms instead of 15 for the curvature's reductions at 640x480)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: list[np.ndarray], b: list[np.ndarray]) -> list[np.ndarray]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _smoothed_members(planes: np.ndarray, member: np.ndarray) -> np.ndarray:
    """Per member pixel, xyz averaged over the member pixels of its CREASE_SMOOTH-square window;
    NaN off the members and where fewer than half of the window are members."""
    weight = member.astype(np.float32)
    count = _box_sum(weight)
    smooth = np.stack([_box_sum(np.where(member, plane, np.float32(0))) for plane in planes])
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth /= count
    smooth[:, ~member | (count <= 0.5 * CREASE_SMOOTH ** 2)] = np.nan
    return smooth


def _box_sum(image: np.ndarray) -> np.ndarray:
    """Sum over each CREASE_SMOOTH-square window (zeros beyond the border), by shifted slices:
    4 ms for the four 640x480 planes where ndimage.uniform_filter took 12."""
    r = CREASE_SMOOTH // 2
    rows = image.copy()
    for k in range(1, r + 1):
        rows[k:] += image[:-k]
        rows[:-k] += image[k:]
    out = rows.copy()
    for k in range(1, r + 1):
        out[:, k:] += rows[:, :-k]
        out[:, :-k] += rows[:, k:]
    return out
