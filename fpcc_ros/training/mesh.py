"""Part meshes: loading, validation, the geometric center and d_max, and pybullet shapes.

The paper's center score is built around the part's "geometric center". We take it to be the
centroid: the center of mass of the solid (uniform density) when the mesh is a closed volume,
else the area-weighted centroid of the surface. Unlike the bounding-box center it does not move
with the mesh's orientation in its file, and for a closed part it is also where pybullet's body
frame sits (we re-center the mesh on it), so the simulated pose gives the center directly.
``d_max`` is the largest distance from that center to any vertex (the paper's normaliser of the
center score and the runtime ``part_radius``).
"""
from __future__ import annotations

import contextlib
import hashlib
import heapq
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}

COLLISION_VERSION = b"decompose-v1"  # part of the cache key: bump when the decomposition changes
MAX_EXTENT_M = 5.0     # larger than any binned part: almost surely a unit mistake
MIN_EXTENT_M = 0.002   # smaller than any part a depth camera resolves


class MeshError(ValueError):
    """A mesh that cannot be used as a part (missing, empty, flat, wrong units)."""


@dataclass(frozen=True, eq=False)
class PartModel:
    """A rigid part: triangle mesh in metres (its own frame), geometric center and d_max."""
    name: str
    vertices: np.ndarray          # (V, 3) float64, metres, mesh frame
    faces: np.ndarray             # (F, 3) int64
    center: np.ndarray            # (3,) geometric center in the mesh frame
    d_max: float                  # max distance center -> vertex (m)
    center_kind: str = "volume"   # "volume" (closed mesh) or "surface"
    source: str = ""              # file path or "builtin:<name>"
    volume: float = field(default=0.0)

    @property
    def extents(self) -> np.ndarray:
        """Axis-aligned bounding-box size in the mesh frame (m)."""
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)

    def centered_vertices(self) -> np.ndarray:
        """Vertices with the geometric center at the origin (the simulation's body frame)."""
        return self.vertices - self.center

    def to_trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices.copy(), self.faces.copy(), process=False)


def geometric_center(mesh: trimesh.Trimesh) -> tuple[np.ndarray, str]:
    """Centroid of the solid if the mesh is a closed volume, else of its surface area."""
    if mesh.is_watertight and abs(mesh.volume) > 0:
        m = mesh.copy()
        if m.volume < 0:
            m.invert()
        return np.asarray(m.center_mass, float), "volume"
    w = mesh.area_faces
    return (mesh.triangles_center * w[:, None]).sum(axis=0) / w.sum(), "surface"


def part_from_trimesh(mesh: trimesh.Trimesh, name: str, source: str = "") -> PartModel:
    """Validate a mesh in metres and compute its geometric center and d_max."""
    label = source or name
    if mesh is None or len(mesh.faces) == 0 or len(mesh.vertices) < 4:
        raise MeshError(f"mesh {label} is empty (no triangles): check the file export")
    v = np.asarray(mesh.vertices, float)
    if not np.all(np.isfinite(v)):
        raise MeshError(f"mesh {label} has non-finite vertex coordinates: check the file export")
    ext = v.max(axis=0) - v.min(axis=0)
    if ext.max() > MAX_EXTENT_M:
        raise MeshError(f"mesh {label} is {ext.max():.3g} m long after unit conversion: check units "
                        f"(a file in millimetres needs --unit mm)")
    if ext.max() < MIN_EXTENT_M:
        raise MeshError(f"mesh {label} has no volume: largest extent {ext.max():.3g} m; "
                        f"check units/export (a file in metres needs --unit m)")
    if ext.min() < 1e-3 * ext.max() or mesh.area <= 0:
        raise MeshError(f"mesh {label} has no volume: it is flat (extents {np.round(ext, 6).tolist()} m); "
                        f"check units/export")
    if mesh.is_watertight and abs(mesh.volume) < 1e-6 * float(np.prod(ext)):
        raise MeshError(f"mesh {label} has no volume: closed mesh encloses {abs(mesh.volume):.3g} m^3; "
                        f"check units/export")
    center, kind = geometric_center(mesh)
    d_max = float(np.linalg.norm(v - center, axis=1).max())
    vol = abs(float(mesh.volume)) if mesh.is_watertight else 0.0
    return PartModel(name=name, vertices=v, faces=np.asarray(mesh.faces, np.int64), center=center,
                     d_max=d_max, center_kind=kind, source=source or f"builtin:{name}", volume=vol)


def load_mesh(path: str | os.PathLike, unit: str = "m", scale: float = 1.0,
              name: str | None = None) -> PartModel:
    """Load an STL/OBJ/PLY (any format trimesh reads) as a part in metres.

    ``unit`` is the file's length unit (m, cm, mm, in); ``scale`` multiplies on top of it.
    Multi-body files are concatenated into one part.
    """
    p = Path(path)
    if unit not in UNITS:
        raise MeshError(f"unit {unit!r} is not supported; use one of {', '.join(UNITS)}")
    if not np.isfinite(scale) or scale <= 0:
        raise MeshError(f"scale must be a positive number, got {scale}")
    if not p.is_file():
        raise MeshError(f"mesh file not found: {p}")
    try:
        mesh = trimesh.load(str(p), force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"mesh {p} could not be read: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f"mesh {p} is empty (no triangles): check the file export")
    # OBJ files split vertices by normal/uv; merge them so closed parts are watertight again
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh.apply_scale(UNITS[unit] * scale)
    return part_from_trimesh(mesh, name=name or p.stem, source=str(p))


# --------------------------------------------------------------------------------------------
# pybullet shapes
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CollisionAssets:
    """OBJ files for pybullet, both in the part's centered frame (origin = geometric center)."""
    visual_obj: str
    collision_obj: str
    kind: str  # "hull" (one convex hull), "decompose" or "vhacd" (compound of convex pieces)


def default_cache_dir() -> Path:
    return Path(tempfile.gettempdir()) / "fpcc_ros_collision"


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C-level stdout (pybullet's vhacd prints its progress there)."""
    try:
        fd = os.dup(1)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(fd, 1)
        os.close(fd)


def _atomic_export(mesh: trimesh.Trimesh, path: Path) -> None:
    tmp = path.with_suffix(f".{os.getpid()}.tmp.obj")
    mesh.export(str(tmp), file_type="obj")
    os.replace(tmp, path)


def convex_decomposition(mesh: trimesh.Trimesh, concavity: float = 0.03, voxels: int = 48,
                         max_pieces: int = 32, seed: int = 0) -> list[np.ndarray]:
    """Approximate convex decomposition: a list of (n_i, 3) point sets, one convex piece each.

    Fast and deterministic (pybullet's V-HACD takes 15-35 s on flat rotational parts such as
    rings, flanges and pulleys: it voxelises them to 2-10 million cells). The part is voxelised
    (``voxels`` cells along its longest side, interior filled), then split recursively: a piece
    is kept when the hull of its cells is at most ``hull_ratio`` times their volume, otherwise it
    is cut into connected components or, if connected, in two by the plane through its centroid
    normal to its principal axis (a ring becomes arcs, an L bracket its legs). Each piece's hull
    is built from exact surface points (mesh vertices and area samples) falling in its cells.
    """
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError
    pitch = float(mesh.extents.max()) / voxels
    lo = mesh.bounds[0] - 2 * pitch
    count = int(np.clip(8 * mesh.area / pitch ** 2, 2_000, 200_000))
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    surf = np.vstack([np.asarray(mesh.vertices), samples])
    ijk = np.floor((surf - lo) / pitch).astype(np.int64)
    occ = np.zeros(tuple(ijk.max(axis=0) + 3), bool)
    occ[tuple(ijk.T)] = True
    # close pinholes in the sampled shell (dilate, fill, erode) so the inside is filled
    filled = ndimage.binary_fill_holes(ndimage.binary_dilation(occ))
    occ |= ndimage.binary_erosion(filled, border_value=0)
    cells = np.argwhere(occ)
    cell_id = np.full(occ.shape, -1, np.int64)
    cell_id[tuple(cells.T)] = np.arange(len(cells))
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])

    def hull_volume(idx: np.ndarray) -> float:
        pts = (cells[idx][:, None, :] + corners[None]).reshape(-1, 3)
        try:
            return ConvexHull(np.unique(pts, axis=0)).volume
        except QhullError:
            return 0.0

    def components(idx: np.ndarray) -> list[np.ndarray]:
        c = cells[idx]
        base = c.min(axis=0)
        grid = np.zeros(tuple(c.max(axis=0) - base + 1), bool)
        grid[tuple((c - base).T)] = True
        lab, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
        which = lab[tuple((c - base).T)]
        return [idx[which == k] for k in range(1, n + 1)]

    def entry(idx: np.ndarray) -> tuple:
        excess = hull_volume(idx) - len(idx) if len(idx) > 8 else 0.0  # in voxel volumes
        return (-excess, int(idx[0]), idx)

    # split the piece with the largest concavity (hull volume minus its own) until every piece
    # is within ``concavity`` of the part's volume, or the piece budget is spent
    tol = concavity * len(cells)
    heap = [entry(c) for c in components(np.arange(len(cells)))]
    heapq.heapify(heap)
    while heap and -heap[0][0] > tol and len(heap) < max_pieces:
        _, _, idx = heapq.heappop(heap)
        x = cells[idx].astype(float)
        mu = x.mean(axis=0)
        axis = np.linalg.eigh(np.cov((x - mu).T))[1][:, -1]
        side = (x - mu) @ axis > 0
        for half in (idx[~side], idx[side]):
            for comp in components(half):
                heapq.heappush(heap, entry(comp))
    pieces = [e[2] for e in sorted(heap, key=lambda e: e[1])]
    piece_of_cell = np.full(len(cells), -1, np.int64)
    for k, idx in enumerate(pieces):
        piece_of_cell[idx] = k
    # hull points: exact surface points, plus the centers of cells holding no surface (at least
    # half a cell inside the part) so pieces cut out of a solid keep their interior side
    surface_cell = np.zeros(len(cells), bool)
    surface_cell[cell_id[tuple(ijk.T)]] = True
    inner = ~surface_cell
    pts_all = np.vstack([surf, lo + (cells[inner] + 0.5) * pitch])
    owner = np.concatenate([piece_of_cell[cell_id[tuple(ijk.T)]], piece_of_cell[inner]])
    grid_key = np.floor((pts_all - lo) / (pitch / 1.5)).astype(np.int64)  # thin out dense samples
    out = []
    for k in range(len(pieces)):
        mine = owner == k
        _, first = np.unique(grid_key[mine], axis=0, return_index=True)
        pts = pts_all[mine][np.sort(first)]
        if len(pts) < 4:
            continue
        try:
            hull = ConvexHull(pts)
        except QhullError:
            continue
        out.append(pts[hull.vertices])
    return out


def _write_pieces_obj(pieces: list[np.ndarray], path: Path) -> None:
    """One OBJ object per convex piece (pybullet loads the file as a compound of hulls)."""
    lines, base = [], 1
    for k, pts in enumerate(pieces):
        hull = trimesh.convex.convex_hull(pts)
        lines.append(f"o piece_{k}")
        lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in hull.vertices]
        lines += [f"f {a + base} {b + base} {c + base}" for a, b, c in hull.faces]
        base += len(hull.vertices)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.obj")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)


def prepare_collision(part: PartModel, cache_dir: str | os.PathLike | None = None,
                      hull_ratio: float = 1.5, method: str = "auto") -> CollisionAssets:
    """Write (or reuse from the cache) the visual and collision OBJs of a part.

    ``method`` "auto": compact parts collide as one convex hull (fast); parts whose hull is more
    than ``hull_ratio`` times their volume (rings, brackets, pipes, open meshes) as a compound
    of convex pieces from ``convex_decomposition``, so rings and hooks can interlock. "hull",
    "decompose" and "vhacd" (pybullet's V-HACD; slow on flat parts) force one. Results are
    cached by mesh content.
    """
    if method not in ("auto", "hull", "decompose", "vhacd"):
        raise ValueError(f"collision method {method!r}: use auto, hull, decompose or vhacd")
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    v = np.ascontiguousarray(part.centered_vertices(), np.float64)
    f = np.ascontiguousarray(part.faces, np.int64)
    mesh = trimesh.Trimesh(v, f, process=False)
    if method == "auto":
        ratio = mesh.convex_hull.volume / part.volume if part.volume > 0 else np.inf
        method = "hull" if ratio <= hull_ratio else "decompose"
    key = hashlib.sha1(v.tobytes() + f.tobytes() + COLLISION_VERSION).hexdigest()[:16]
    visual = cache / f"{key}_visual.obj"
    collision = cache / f"{key}_{method}.obj"
    if not visual.exists():
        _atomic_export(mesh, visual)
    if collision.exists():
        return CollisionAssets(str(visual), str(collision), method)
    if method == "hull":
        _atomic_export(mesh.convex_hull, collision)
    elif method == "decompose":
        pieces = convex_decomposition(mesh)
        if not pieces:  # degenerate: one hull still collides
            return prepare_collision(part, cache, hull_ratio, "hull")
        _write_pieces_obj(pieces, collision)
    else:
        import pybullet as p  # training-only dependency
        tmp = collision.with_suffix(f".{os.getpid()}.tmp.obj")
        with _quiet_stdout():
            p.vhacd(str(visual), str(tmp), os.devnull)
        if not tmp.exists() or tmp.stat().st_size == 0:
            return prepare_collision(part, cache, hull_ratio, "hull")
        os.replace(tmp, collision)
    return CollisionAssets(str(visual), str(collision), method)


def create_part_shapes(client: int, assets: CollisionAssets) -> tuple[int, int]:
    """Create the (collision, visual) shape ids of a part in a pybullet client (reused per copy)."""
    import pybullet as p
    col = p.createCollisionShape(p.GEOM_MESH, fileName=assets.collision_obj, physicsClientId=client)
    vis = p.createVisualShape(p.GEOM_MESH, fileName=assets.visual_obj, physicsClientId=client)
    if col < 0 or vis < 0:
        raise MeshError(f"pybullet could not load {assets.collision_obj} / {assets.visual_obj}")
    return col, vis
